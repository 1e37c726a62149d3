"""`hapticlink library …`: build, list and render from the command line."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.io import wavfile

from service.cli import main as hapticlink


@pytest.fixture(scope="module")
def lib_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("lib") / "synthetic"
    assert hapticlink(["library", "build-synthetic", "--out", str(out), "--n-textures", "2", "--seed", "3"]) == 0
    return out


def test_list_prints_every_entry(lib_dir, capsys):
    capsys.readouterr()
    assert hapticlink(["library", "list", str(lib_dir)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:2] == ["id", "group"] and len(lines) == 3
    assert lines[1].startswith("synth_000") and lines[2].rstrip().endswith("ground-truth")
    # the flag `render` takes names the library here too: it fell to the top-level usage
    assert hapticlink(["library", "list", "--library", str(lib_dir)]) == 0
    assert capsys.readouterr().out.splitlines() == lines
    assert hapticlink(["library", "list"]) == 2
    assert "name the library directory once" in capsys.readouterr().err


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".wav"])
def test_render_writes_the_requested_length(lib_dir, tmp_path, suffix, capsys):
    out = tmp_path / f"a{suffix}"
    assert (
        hapticlink(
            [
                "library",
                "render",
                "synth_001",
                "--library",
                str(lib_dir),
                "--speed",
                "120",
                "--force",
                "2",
                "--seconds",
                "0.5",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    if suffix == ".npy":
        data = np.load(out)
    elif suffix == ".csv":
        table = np.loadtxt(out, delimiter=",", skiprows=1)
        np.testing.assert_allclose(table[:3, 0], [0.0, 0.001, 0.002])
        data = table[:, 1]
    else:
        rate, data = wavfile.read(out)
        assert rate == 1000 and data.dtype == np.float32
    assert data.shape == (500,) and data.std() > 0
    assert "rendered 500 samples" in capsys.readouterr().out


def test_render_mentions_clamping_and_refuses_bad_arguments(lib_dir, tmp_path, capsys):
    args = ["library", "render", "synth_000", "--library", str(lib_dir), "--seconds", "0.1"]
    assert hapticlink(args + ["--speed", "9999", "--force", "1", "--out", str(tmp_path / "a.npy")]) == 0
    assert "clamped to the model's range" in capsys.readouterr().out
    assert hapticlink(args + ["--speed", "100", "--force", "1", "--out", str(tmp_path / "a.mp3")]) == 2
    assert "--out must end in .wav, .csv or .npy" in capsys.readouterr().err
    assert hapticlink(args + ["--speed", "-1", "--force", "1", "--out", str(tmp_path / "a.npy")]) == 2
    assert (
        hapticlink(
            [
                "library",
                "render",
                "nope",
                "--library",
                str(lib_dir),
                "--speed",
                "1",
                "--force",
                "1",
                "--out",
                str(tmp_path / "a.npy"),
            ]
        )
        == 2
    )
    assert "no entry 'nope'" in capsys.readouterr().err
