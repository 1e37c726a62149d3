"""The taps feature group in datasets: each texture's tap transients become a per-texture feature block."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.offline.datasets.format import Dataset
from models.offline.featurize import tactile_table, texture_tap_features
from models.tactile.config import TactileConfig
from models.tactile.taps import tap_features
from texture_library.vibration import VibrationModel


def test_tap_features_are_the_same_on_every_window_of_a_texture(dataset_copy):
    config = TactileConfig(extra_groups=("friction", "taps"))
    table = tactile_table(dataset_copy, config, workers=1)
    taps_cols = table.X[:, config.group_slices()["taps"]]
    ds = Dataset(dataset_copy)
    for i, texture in enumerate(table.textures):
        taps = ds.taps(texture)
        expected = tap_features(taps.speeds, taps.accel)
        np.testing.assert_allclose(taps_cols[table.texture == i], np.tile(expected, (2, 1)), rtol=1e-6)
    # the synthetic world's friction is each texture's μ
    mus = [ds.meta(t).extra["physical"]["mu"] for t in table.textures]
    ratio = table.X[:, config.group_slices()["friction"]][:, 0]
    np.testing.assert_allclose([ratio[table.texture == i].mean() for i in range(3)], mus, atol=0.02)


def test_a_texture_without_taps_is_named(dataset_copy):
    ds = Dataset(dataset_copy)
    path = ds.vibration_model_path("synth_001")
    VibrationModel.save(dataclasses.replace(VibrationModel.load(path), taps=None), path)
    with pytest.raises(ValueError, match="'synth_001' has no tap transients"):
        texture_tap_features(ds, "synth_001")
    with pytest.raises(ValueError, match="no tap transients"):
        tactile_table(dataset_copy, TactileConfig(extra_groups=("taps",)), workers=1)
    # other groups do not need taps
    assert tactile_table(dataset_copy, TactileConfig(extra_groups=("spatial",)), workers=1).X.shape == (6, 548)
