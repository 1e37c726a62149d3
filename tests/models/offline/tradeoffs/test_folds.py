import numpy as np
import pytest

from models.offline.tradeoffs.folds import calibration_keys, calibration_sources, inner_folds, key_excludes, partition


def test_partition_is_balanced_and_fixed():
    part = partition(79, 10, seed=0)
    assert np.bincount(part).min() == 7 and np.bincount(part).max() == 8
    np.testing.assert_array_equal(part, partition(79, 10, seed=0))
    with pytest.raises(ValueError):
        partition(5, 10)


def test_every_calibration_model_saw_neither_the_held_out_texture_nor_the_one_it_predicts():
    part = partition(40, 5, seed=1)
    keys = set(calibration_keys(5))
    assert len(keys) == 5 + 10
    for i in range(40):
        sources = calibration_sources(part, i)
        assert sorted(j for j, _ in sources) == [j for j in range(40) if j != i]
        for j, key in sources:
            assert key in keys
            excluded = key_excludes(part, key)
            assert excluded[i] and excluded[j]  # trained without i and without j


def test_inner_folds_cover_the_training_textures_once():
    train = np.array([0, 2, 3, 5, 8, 9, 11])
    folds = inner_folds(train, 3)
    np.testing.assert_array_equal(np.sort(np.concatenate(folds)), train)
