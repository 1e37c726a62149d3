"""Tactile feature tables of a dataset, and their cache."""

from __future__ import annotations

import json

import numpy as np
import pytest

import models.offline.featurize as featurize
from models.offline.datasets.format import Dataset
from models.offline.featurize import dataset_fingerprint, tactile_table
from models.tactile.config import TactileConfig


def test_tactile_table_shapes(dataset_copy):
    table = tactile_table(dataset_copy, workers=1)
    # 3 textures × one 2 s recording, 0.5 s cropped at both ends → 1 s → two 0.5 s windows each
    assert table.textures == ["synth_000", "synth_001", "synth_002"]
    assert table.X.shape == (6, 526) and table.X.dtype == np.float32
    np.testing.assert_array_equal(table.texture, [0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(table.recording, 0)
    np.testing.assert_allclose(table.t_start, [0.5, 1.0] * 3)
    assert np.isfinite(table.X).all()
    assert table.config == TactileConfig()


def test_second_call_loads_the_cache(dataset_copy, monkeypatch):
    first = tactile_table(dataset_copy, workers=1)
    (cache,) = (dataset_copy / "features").glob("tactile-*.npz")
    assert cache.name == f"tactile-{TactileConfig().hash()}-{dataset_fingerprint(Dataset(dataset_copy))}.npz"

    def no_computing(*args, **kwargs):
        raise AssertionError("features were recomputed instead of read from the cache")

    monkeypatch.setattr(featurize, "run_jobs", no_computing)
    second = tactile_table(dataset_copy, workers=1)
    np.testing.assert_array_equal(second.X, first.X)
    np.testing.assert_array_equal(second.texture, first.texture)
    np.testing.assert_array_equal(second.t_start, first.t_start)


def test_a_changed_config_gets_its_own_cache_file(dataset_copy):
    tactile_table(dataset_copy, workers=1)
    halves = tactile_table(dataset_copy, TactileConfig(hop_s=0.25), workers=1)
    assert len(list((dataset_copy / "features").glob("tactile-*.npz"))) == 2
    assert halves.X.shape == (9, 526)  # windows at 0.5, 0.75, 1.0 s per texture
    assert halves.config.hop_s == 0.25


def test_a_rebuilt_dataset_does_not_reuse_stale_features(dataset_copy):
    tactile_table(dataset_copy, workers=1)
    header_path = dataset_copy / "dataset.json"
    header = json.loads(header_path.read_text())
    header["build"]["seed"] = 99  # what a rebuild with another seed changes
    header_path.write_text(json.dumps(header))
    tactile_table(dataset_copy, workers=1)
    assert len(list((dataset_copy / "features").glob("tactile-*.npz"))) == 2


def test_a_recording_with_no_complete_window_is_named(dataset_copy):
    header_path = dataset_copy / "dataset.json"
    header = json.loads(header_path.read_text())
    header["build"]["crop_s"] = 0.9  # 2 s − 2 × 0.9 s leaves 0.2 s
    header_path.write_text(json.dumps(header))
    with pytest.raises(
        ValueError,
        match=r"texture 'synth_000', recording_000.npz \(crop_s=0.9 s at both ends\): .*holds no complete 0.5 s window",
    ):
        tactile_table(dataset_copy, workers=1)


def test_run_jobs_keeps_job_order_in_worker_processes():
    import math

    from models.offline.jobs import run_jobs

    assert list(run_jobs(math.sqrt, [1.0, 4.0, 9.0, 16.0, 25.0], 2, "roots")) == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert list(run_jobs(math.sqrt, [4.0], None, "one")) == [2.0]
