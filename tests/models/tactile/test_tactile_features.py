import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.tactile.config import TactileConfig
from models.tactile.dft321 import dft321
from models.tactile.features import recording_features, window_features
from models.tactile.mfcc import mfcc
from models.tactile.preprocess import TactilePreprocessor
from texture_library.recording import Channel

REPO = Path(__file__).resolve().parents[3]


@pytest.mark.parametrize("hop_s", [0.5, 0.25])
@pytest.mark.parametrize("duration", [2.0, 3.7])
def test_recording_features_shape_dtype_and_count(duration, hop_s, make_recording):
    config = TactileConfig(hop_s=hop_s)
    feats, t0 = recording_features(make_recording(duration, 3000.0, 500.0, 200.0), config)
    n_win = math.floor((duration - 0.5) / hop_s + 1e-9) + 1
    assert feats.shape == (n_win, 526) and feats.dtype == np.float32
    np.testing.assert_allclose(t0, hop_s * np.arange(n_win))
    assert np.all(np.isfinite(feats))


@settings(max_examples=15, deadline=None)
@given(
    sizes=st.lists(st.integers(1, 1500), min_size=1, max_size=6),
    motion=st.sampled_from(["speed", "position"]),
    feature_set=st.sampled_from(["mfcc", "dwt", "dft"]),
    groups=st.sampled_from([(), ("friction", "spatial")]),
)
def test_train_serve_equivalence(sizes, motion, feature_set, groups, make_recording):
    """Serving pushes blocks and featurises each window alone; training featurises the recording
    (the derived streams of the extra groups included)."""
    config = TactileConfig(feature_set=feature_set, extra_groups=groups)
    rec = make_recording(2.5, 2000.0, 1000.0, 500.0, force_axes=3, motion=motion, seed=3)
    offline, t0 = recording_features(rec, config)
    pre = TactilePreprocessor(config)
    served, starts = [], []
    channels = rec.channels()
    pos = dict.fromkeys(channels, 0)
    k = 0
    while any(pos[n] < c.data.shape[0] for n, c in channels.items()):
        block = {}
        for n, c in channels.items():
            size = max(1, int(sizes[k % len(sizes)] * c.rate_hz / 1000.0))
            if pos[n] < c.data.shape[0]:
                block[n] = Channel(c.data[pos[n] : pos[n] + size], c.rate_hz)
            pos[n] += size
        k += 1
        pre.push(**block)
        for w in pre.windows():
            served.append(window_features(w.accel[None], w.speed[None], w.force[None], config)[0])
            starts.append(w.t_start_s)
    pre.flush()
    for w in pre.windows():
        served.append(window_features(w.accel[None], w.speed[None], w.force[None], config)[0])
        starts.append(w.t_start_s)
    assert len(served) == offline.shape[0] == 5
    np.testing.assert_allclose(np.stack(served), offline, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(starts, t0)


def test_window_features_layout():
    config = TactileConfig()
    rng = np.random.default_rng(4)
    accel = rng.standard_normal((3, 500, 3))
    speed = 50 + rng.standard_normal((3, 500))
    force = 2 + rng.standard_normal((3, 500))
    f = window_features(accel, speed, force, config)
    assert f.shape == (3, 526) and f.dtype == np.float32
    np.testing.assert_allclose(f[:, :520], mfcc(dft321(accel), config).reshape(3, 520), rtol=1e-5, atol=1e-4)
    stats = np.column_stack([speed.min(1), speed.max(1), speed.mean(1), force.min(1), force.max(1), force.mean(1)])
    np.testing.assert_allclose(f[:, 520:], stats, rtol=1e-6)
    assert window_features(accel[:0], speed[:0], force[:0], config).shape == (0, 526)


@pytest.mark.parametrize(("feature_set", "width"), [("dwt", 24), ("dft", 38)])
def test_other_feature_sets(feature_set, width, make_recording):
    config = TactileConfig(feature_set=feature_set)
    feats, _ = recording_features(make_recording(1.5), config)
    assert feats.shape == (3, width) == (3, len(config.feature_names))


def test_skip_and_stop(make_recording):
    rec = make_recording(5.0)
    config = TactileConfig()
    feats, t0 = recording_features(rec, config, skip_s=2.5, stop_s=4.5)
    np.testing.assert_allclose(t0, [2.5, 3.0, 3.5, 4.0])
    full, _ = recording_features(rec, config)
    np.testing.assert_array_equal(feats, full[5:9])


def test_bad_inputs(make_recording):
    config = TactileConfig()
    ok = (np.zeros((2, 500, 3)), np.zeros((2, 500)), np.zeros((2, 500)))
    with pytest.raises(ValueError, match=r"accel must have shape \(n, 500, 3\)"):
        window_features(np.zeros((2, 400, 3)), *ok[1:], config)
    with pytest.raises(ValueError, match=r"speed must have shape \(2, 500\)"):
        window_features(ok[0], np.zeros((3, 500)), ok[2], config)
    with pytest.raises(ValueError, match="force has 2 NaN or Inf"):
        window_features(*ok[:2], np.where(np.arange(500) == 7, np.nan, 0.0)[None].repeat(2, 0), config)
    with pytest.raises(ValueError, match="no complete 0.5 s window"):
        recording_features(make_recording(0.4), config)
    with pytest.raises(ValueError, match="no complete"):
        recording_features(make_recording(3.0), config, skip_s=2.8)
    with pytest.raises(ValueError, match="stop_s"):
        recording_features(make_recording(3.0), config, skip_s=1.0, stop_s=0.5)
    with pytest.raises(ValueError, match="recording must be"):
        recording_features({"accel": None}, config)  # type: ignore[arg-type]


def test_tactile_package_never_imports_torch():
    code = "import sys, models.tactile.features, models.tactile.preprocess; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=REPO).returncode == 0
    for path in (REPO / "models" / "tactile").glob("*.py"):
        assert "torch" not in path.read_text(), path
