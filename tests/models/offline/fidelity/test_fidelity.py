"""`hapticlink fidelity`: every rule scored leave-one-texture-out on a small synthetic world, the hybrid's
weight chosen without the held-out texture, and a results.json that keeps the other studies' keys."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from models.offline.fidelity import study
from models.offline.fidelity.cli import register
from models.offline.provenance import file_sha256
from texture_library.attributes import ATTRIBUTES


@pytest.fixture(scope="module")
def world_files(tmp_path_factory):
    from models.offline.datasets.build import build
    from models.offline.datasets.format import Dataset

    root = tmp_path_factory.mktemp("fidelity")
    dataset = build("synthetic", root / "dataset", n_textures=6, duration_s=4)
    means = Dataset(dataset).mean_ratings()
    rng = np.random.default_rng(0)
    predictions = {
        t: dict(zip(ATTRIBUTES, map(float, np.clip(r + rng.normal(0, 15, 4), -100, 100)))) for t, r in means.items()
    }
    pred_path = root / "results.json"
    pred_path.write_text(json.dumps({"predictions": predictions}))
    return dataset, pred_path


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_the_report_scores_every_rule_with_intervals_and_keeps_other_keys(world_files, tmp_path):
    dataset, predictions = world_files
    out = tmp_path / "fidelity"
    out.mkdir()
    (out / "results.json").write_text(json.dumps({"bandwidth": {"raw_bps": 48000}}))
    argv = ["fidelity", "--dataset", str(dataset), "--predictions", str(predictions), "--out", str(out)]
    assert run_cli(argv + ["--synthetic-dataset", str(dataset), "--synthetic-predictions", str(predictions)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["bandwidth"] == {"raw_bps": 48000}  # another study's key survives
    assert doc["default_rule"] == "hybrid"
    rules = {r["rule"]: r for r in doc["selection"]}
    assert set(study.RULE_ORDER) <= set(rules)
    for r in doc["selection"]:
        assert r["textures"] == 6
        for metric in study.METRICS:
            lo, hi = r["ci95"][metric]
            assert lo <= r[metric] <= hi
    # the spectral oracle is the floor of spectral distance; the perceptual oracle's rating distance is low
    assert rules["oracle-spectral"]["spectral_distance_db"] <= min(r["spectral_distance_db"] for r in doc["selection"])
    assert rules["oracle-perceptual"]["rating_distance"] < rules["random"]["rating_distance"]
    assert len(doc["selection_synthetic"]) == len(doc["selection"])
    # the inputs it read, with their digests: both predictions files and both dataset manifests
    made = doc["selection_study"]["provenance"]
    by_role = [(i["role"], i["sha256"]) for i in made["inputs"]]
    assert ("predictions", file_sha256(predictions)) in by_role
    assert ("dataset manifest", file_sha256(Path(dataset) / "dataset.json")) in by_role and len(by_role) == 4
    assert made["command"] == doc["selection_study"]["command"]
    readme = (out / "README.md").read_text()
    assert "pareto_hatt.png" in readme and (out / "pareto_hatt.png").stat().st_size > 1000
    assert (out / "pareto_synthetic.png").is_file() and (out / "hybrid_weight.png").is_file()


def test_the_hybrid_weight_is_tuned_without_the_held_out_texture(world_files, monkeypatch):
    dataset, predictions = world_files
    world = study.load_world(dataset, predictions, windows=4)
    seen: list[np.ndarray] = []
    real = study.tune_weight

    def spy(w, train):
        seen.append(train.copy())
        return real(w, train)

    monkeypatch.setattr(study, "tune_weight", spy)
    per_texture, info = study.run_rules(world)
    T = len(world.textures)
    assert len(seen) == T + 1  # one per outer fold, then the served weight on every texture
    for i in range(T):
        assert not seen[i][i] and seen[i].sum() == T - 1
    assert seen[T].all()
    assert len(info["fold_weights"]) == T and all(w in study.WEIGHTS for w in info["fold_weights"])
    # the random rule is the exact mean over the library, not a draw
    off = ~np.eye(T, dtype=bool)
    np.testing.assert_allclose(per_texture["random"]["rating_distance"], (world.rating_d * off).sum(1) / (T - 1))


def test_bad_arguments_get_a_clear_error(world_files, tmp_path, capsys):
    from service.cli import main

    dataset, predictions = world_files
    base = ["fidelity", "--dataset", str(dataset), "--predictions", str(predictions), "--out", str(tmp_path)]
    assert main(base + ["--synthetic-dataset", str(dataset)]) == 2
    assert "hapticlink fidelity: error: --synthetic-dataset and --synthetic-predictions go together" in (
        capsys.readouterr().err
    )
    assert main(base + ["--default-rule", "loudest"]) == 2
    assert "--default-rule must be one of" in capsys.readouterr().err
    assert main(["fidelity", "--dataset", str(tmp_path), "--predictions", str(predictions)]) == 2
    assert f"hapticlink fidelity: error: {tmp_path}: not a hapticlink dataset" in capsys.readouterr().err
