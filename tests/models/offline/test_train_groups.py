"""A model on the physics feature groups: per-group block weights inside the exported ridge graph."""

import numpy as np
import pytest

from models.inference.modelfile import read_card
from models.inference.predictor import Predictor
from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.evaluation.estimator_registry import build_estimator
from models.offline.train import train_and_export
from models.tactile.config import TactileConfig
from service.cli import main as cli

GROUPS = TactileConfig(extra_groups=("friction", "spatial"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build("synthetic", tmp_path_factory.mktemp("ds") / "synthetic", n_textures=8, duration_s=3, image_size=64)


@pytest.mark.slow
def test_exported_ridge_on_groups_equals_the_estimator(dataset, tmp_path):
    path = train_and_export(dataset, "ridge-tactile", tmp_path / "ridge.onnx", seed=0, tactile_config=GROUPS)
    card = read_card(path)
    assert TactileConfig(**card.tactile_config) == GROUPS and card.tactile_hash == GROUPS.hash()
    data = load_texture_data(dataset, tactile_config=GROUPS, visual=False)
    est = build_estimator("ridge-tactile").fit(data, 0)
    assert len(est.features.scalers) == 3  # base, friction, spatial: one weighted block each
    predictor = Predictor(path)
    assert predictor.tactile_config == GROUPS and predictor.n_tactile == GROUPS.n_features
    for i in range(len(data)):
        expected = np.clip(est.predict(data.take([i]))[0], -100, 100)
        np.testing.assert_allclose(predictor.predict(data.tactile[i].mean(axis=0)), expected[None], atol=1e-2)


def test_cli_takes_extra_groups(dataset, tmp_path):
    out = tmp_path / "model.onnx"
    assert (
        cli(
            [
                "train",
                "--dataset",
                str(dataset),
                "--model",
                "ridge-tactile",
                "--extra-groups",
                "spatial",
                "friction",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert TactileConfig(**read_card(out).tactile_config) == GROUPS
    with pytest.raises(SystemExit):
        cli(
            [
                "train",
                "--dataset",
                str(dataset),
                "--model",
                "ridge-tactile",
                "--extra-groups",
                "smell",
                "--out",
                str(out),
            ]
        )
