"""ONNX export: raw-feature parity with torch for every preset, folding, clipping, metadata."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from models.inference.modelfile import read_metadata as load_metadata
from models.inference.standardize import Standardizer
from models.offline.nets import presets
from models.offline.nets.export import export_onnx, raw_model

F_DIM, V_DIM = 526, 64
REPO = Path(__file__).resolve().parents[4]


def stats(rng: np.random.Generator, visual_dim: int = V_DIM) -> dict[str, np.ndarray]:
    return {
        "tactile_mean": rng.normal(size=F_DIM),
        "tactile_std": rng.uniform(0.5, 2.0, F_DIM),
        "visual_mean": rng.normal(size=visual_dim),
        "visual_std": rng.uniform(0.5, 2.0, visual_dim),
        "target_mean": rng.normal(scale=10.0, size=4),
        "target_std": rng.uniform(20.0, 40.0, 4),
    }


def session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def check_parity(name: str, visual_dim: int, tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    model = presets.build(name, visual_dim, F_DIM, seed=0)
    s = stats(rng, visual_dim)
    path = export_onnx(model, tmp_path / f"{name}.onnx", **s, metadata={"model": name})
    sess = session(path)
    names = [i.name for i in sess.get_inputs()]
    expected_inputs = {"both": ["tactile", "visual"], "tactile": ["tactile"], "visual": ["visual"]}[model.modality]
    assert names == expected_inputs
    assert [o.name for o in sess.get_outputs()] == ["ratings"]
    for batch in (1, 7):
        raw = {
            "tactile": (s["tactile_mean"] + s["tactile_std"] * rng.normal(size=(batch, F_DIM))).astype(np.float32),
            "visual": (s["visual_mean"] + s["visual_std"] * rng.normal(size=(batch, visual_dim))).astype(np.float32),
        }
        if batch > 1:  # inputs far outside the training range: the graph bounds z as the estimators do
            raw["tactile"][0, ::5] += 1e3 * s["tactile_std"][::5]
            raw["visual"][1, ::3] -= 1e3 * s["visual_std"][::3]
        got = sess.run(None, {k: raw[k] for k in names})[0]
        # reference straight from the model on standardized inputs, not through the wrapper
        with torch.no_grad():
            t = torch.from_numpy(
                Standardizer.from_stats(s["tactile_mean"], s["tactile_std"])
                .transform(raw["tactile"])
                .astype(np.float32)
            )
            v = torch.from_numpy(
                Standardizer.from_stats(s["visual_mean"], s["visual_std"]).transform(raw["visual"]).astype(np.float32)
            )
            model.eval()
            y = model(t, v)["ratings"].numpy() * s["target_std"] + s["target_mean"]
        expected = np.clip(y, -100, 100)
        assert got.shape == (batch, 4)
        np.testing.assert_allclose(got, expected, atol=1e-3, rtol=0)


@pytest.mark.parametrize("name", [n for n in presets.NAMES if n != "vtnet"])
def test_parity_every_preset(name: str, tmp_path: Path) -> None:
    check_parity(name, V_DIM, tmp_path)


@pytest.mark.slow
def test_parity_faithful_vtnet(tmp_path: Path) -> None:
    check_parity("vtnet", 1536, tmp_path)


def test_ratings_are_clipped_to_the_bipolar_range(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    s = stats(rng)
    s["target_mean"] = np.array([500.0, -500.0, 0.0, 0.0])
    s["target_std"] = np.array([1.0, 1.0, 1e4, 1e4])
    model = presets.build("ann", V_DIM, F_DIM, seed=0)
    path = export_onnx(model, tmp_path / "m.onnx", **s, metadata={})
    y = session(path).run(
        None,
        {
            "tactile": rng.normal(size=(5, F_DIM)).astype(np.float32),
            "visual": rng.normal(size=(5, V_DIM)).astype(np.float32),
        },
    )[0]
    assert np.all(y[:, 0] == 100.0) and np.all(y[:, 1] == -100.0)
    assert np.all(np.abs(y) <= 100.0)


def test_decoder_is_not_in_the_graph(tmp_path: Path) -> None:
    import onnx

    model = presets.build("vtnet-visual", V_DIM, F_DIM, seed=0)
    path = export_onnx(model, tmp_path / "m.onnx", **stats(np.random.default_rng(0)), metadata={})
    convs = [n for n in onnx.load(str(path)).graph.node if n.op_type == "Conv"]
    assert len(convs) == len(model.visual.encoder)  # type: ignore[union-attr]


def test_metadata_roundtrip_and_checks(tmp_path: Path) -> None:
    model = presets.build("vtnet-tactile", V_DIM, F_DIM, seed=0)
    s = stats(np.random.default_rng(0))
    meta = {"feature_config_hash": "abc123", "attributes": "rough_smooth,flat_bumpy,sticky_slippery,hard_soft"}
    path = export_onnx(model, tmp_path / "m.onnx", **s, metadata=meta)
    assert load_metadata(path) == {**meta, "modality": "tactile", "inputs": "tactile"}
    with pytest.raises(ValueError, match="must be strings"):
        export_onnx(model, tmp_path / "x.onnx", **s, metadata={"epochs": 3})  # type: ignore[dict-item]
    with pytest.raises(ValueError, match="contradicts"):
        export_onnx(model, tmp_path / "x.onnx", **s, metadata={"modality": "both"})


def test_bad_statistics_raise() -> None:
    model = presets.build("ann", V_DIM, F_DIM, seed=0)
    s = stats(np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"tactile_std must be > 0"):
        raw_model(model, **{**s, "tactile_std": np.zeros(F_DIM)})
    with pytest.raises(ValueError, match="target_mean has 3 values"):
        raw_model(model, **{**s, "target_mean": np.zeros(3)})
    with pytest.raises(ValueError, match="different lengths"):
        raw_model(model, **{**s, "visual_std": np.ones(V_DIM + 1)})


def test_export_keeps_the_training_mode(tmp_path: Path) -> None:
    model = presets.build("ann", V_DIM, F_DIM, seed=0)
    model.train()
    export_onnx(model, tmp_path / "m.onnx", **stats(np.random.default_rng(0)), metadata={})
    assert model.training


def test_reading_metadata_needs_no_torch(tmp_path: Path) -> None:
    path = export_onnx(
        presets.build("ann", V_DIM, F_DIM, seed=0),
        tmp_path / "m.onnx",
        **stats(np.random.default_rng(0)),
        metadata={"k": "v"},
    )
    code = (
        "import sys\n"
        "from models.inference.modelfile import read_metadata as load_metadata\n"
        "from models.offline.nets.latency import onnx_latency\n"
        f"assert load_metadata({str(path)!r})['k'] == 'v'\n"
        f"onnx_latency({str(path)!r}, n=2)\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
