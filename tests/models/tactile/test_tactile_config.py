import json
import warnings

import librosa
import pytest

from models.tactile.config import STAT_NAMES, TactileConfig, mel_filter_sizes


def test_defaults_give_the_papers_sizes():
    c = TactileConfig()
    assert (c.window_length, c.hop_length) == (500, 500)
    assert c.n_frames == 1 + (500 - 25) // 12 == 40
    assert c.n_features == 40 * 13 + 6 == 526
    names = c.feature_names
    assert len(names) == len(set(names)) == 526
    assert names[:2] == ["mfcc_f00_c00", "mfcc_f00_c01"] and names[519] == "mfcc_f39_c12"
    assert (
        names[-6:]
        == list(STAT_NAMES)
        == ["speed_min", "speed_max", "speed_mean", "force_min", "force_max", "force_mean"]
    )


@pytest.mark.parametrize(("feature_set", "n_tactile"), [("dwt", 3 * 6), ("dft", 32)])
def test_other_feature_sets_sizes(feature_set, n_tactile):
    c = TactileConfig(feature_set=feature_set)
    assert c.n_features == n_tactile + 6 == len(c.feature_names) == len(set(c.feature_names))


def test_default_mel_filterbank_has_no_empty_filter():
    c = TactileConfig()
    sizes = mel_filter_sizes(c.rate_hz, c.n_fft, c.n_mels, c.fmin, c.fmax)
    assert len(sizes) == 26 and min(sizes) >= 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # librosa warns on empty filters
        basis = librosa.filters.mel(sr=c.rate_hz, n_fft=c.n_fft, n_mels=c.n_mels, fmin=c.fmin, fmax=c.fmax)
    assert (basis.max(axis=1) > 0).all()


@pytest.mark.parametrize(("n_fft", "n_mels"), [(25, 26), (32, 32), (26, 26)])
def test_config_with_empty_mel_filters_is_rejected(n_fft, n_mels):
    # n_fft = frame_length = 25: the paper's setting taken literally (13 bins for 26 bands)
    assert min(mel_filter_sizes(1000.0, n_fft, n_mels, 20.0, 500.0)) == 0
    with pytest.raises(ValueError, match="empty filter"):
        TactileConfig(n_fft=n_fft, n_mels=n_mels)


def test_smaller_ffts_leave_single_bin_filters():
    # why 64: 32 and 48 are legal but leave some bands a single bin wide
    assert min(mel_filter_sizes(1000.0, 32, 26, 20.0, 500.0)) == 1
    assert min(mel_filter_sizes(1000.0, 48, 26, 20.0, 500.0)) == 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"fmax": 600.0}, "fmax"),
        ({"fmin": 500.0}, "fmin < fmax"),
        ({"hop_s": 0.0}, "hop_s"),
        ({"window_s": -1.0}, "window_s"),
        ({"window_s": 0.5004}, "whole number of samples"),
        ({"frame_length": 80}, r"frame_length \(80\) must be ≤ n_fft"),
        ({"frame_hop": 0}, "frame_hop"),
        ({"n_mfcc": 30}, "n_mfcc"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"rate_hz": 1e9}, "rate_hz"),
        ({"accel_highpass_hz": 500.0}, "accel_highpass_hz"),
        ({"lowpass_order": 0}, "lowpass_order"),
        ({"top_db": -1.0}, "top_db"),
        ({"dwt_levels": 9}, "dwt_levels"),
        ({"dft_bins": 400}, "dft_bins"),
        ({"unknown": 1}, "unknown"),
    ],
)
def test_bad_configs_name_the_problem(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TactileConfig(**kwargs)


def test_frozen():
    c = TactileConfig()
    with pytest.raises(ValueError):
        c.n_mels = 40  # type: ignore[misc]


def test_hash_is_stable_and_sensitive():
    c = TactileConfig()
    h = c.hash()
    assert len(h) == 16 and int(h, 16) >= 0
    assert TactileConfig().hash() == h
    assert TactileConfig(**json.loads(json.dumps(c.to_dict()))).hash() == h
    assert TactileConfig(**c.to_dict()) == c
    changed = {
        TactileConfig(n_mels=20).hash(),
        TactileConfig(hop_s=0.25).hash(),
        TactileConfig(feature_set="dwt").hash(),
    }
    assert h not in changed and len(changed) == 3
