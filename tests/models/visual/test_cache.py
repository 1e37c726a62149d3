import numpy as np
import pytest

from models.visual.augment import IDENTITY_VIEW
from models.visual.cache import FeatureCache, cache_key


@pytest.fixture
def image():
    return np.random.default_rng(0).random((32, 32)).astype(np.float32)


def _key(image, **changes):
    parts = {
        "view": IDENTITY_VIEW,
        "config_hash": "c" * 16,
        "backbone_name": "efficientnet_lite0",
        "weights_fingerprint": "f" * 16,
    }
    parts.update(changes)
    return cache_key(image, parts["view"], parts["config_hash"], parts["backbone_name"], parts["weights_fingerprint"])


def test_key_covers_every_input(image):
    base = _key(image)
    assert len(base) == 64 and base == _key(image.copy())
    assert _key(image.astype(np.float64)) == base  # hashed as float32
    changed = image.copy()
    changed[3, 4] += 1e-3
    others = {
        _key(changed),
        _key(image.reshape(16, 64)),
        _key(image, view={**IDENTITY_VIEW, "rot90": 1}),
        _key(image, config_hash="d" * 16),
        _key(image, backbone_name="resnet50"),
        _key(image, weights_fingerprint="0" * 16),
    }
    assert base not in others and len(others) == 6


def test_round_trip_and_layout(tmp_path, image):
    cache = FeatureCache(tmp_path / "deep" / "cache")
    key = _key(image)
    assert cache.get(key) is None and key not in cache
    values = np.random.default_rng(1).random(1536).astype(np.float32)
    path = cache.put(key, values)
    assert path == tmp_path / "deep" / "cache" / key[:2] / f"{key}.npy"
    assert key in cache
    got = cache.get(key)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, values)
    # overwrite is atomic and leaves no temporary files behind
    cache.put(key, values * 2)
    np.testing.assert_array_equal(cache.get(key), values * 2)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_unreadable_entry_is_a_miss(tmp_path, image):
    cache = FeatureCache(tmp_path)
    key = _key(image)
    cache.path_for(key).parent.mkdir(parents=True)
    cache.path_for(key).write_bytes(b"garbage")
    assert cache.get(key) is None


def test_default_root_is_cache_visual_under_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert FeatureCache().root == tmp_path.resolve() / "cache" / "visual"


def test_bad_keys_raise(tmp_path):
    with pytest.raises(ValueError, match="64 lowercase hex"):
        FeatureCache(tmp_path).path_for("../../etc/passwd")
