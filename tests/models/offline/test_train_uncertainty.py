"""`hapticlink train` calibrates intervals and fits an OOD detector into the model card; the serving
side rebuilds them from the card (numpy only) and uses them window by window."""

import numpy as np
import pytest

from models.inference.intervals import EmaUncertainty, calibrations_from_card, ema, ema_flags
from models.inference.modelfile import read_card
from models.inference.ood import OODDetector
from models.inference.predictor import Predictor
from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.train import train_and_export


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build("synthetic", tmp_path_factory.mktemp("ds") / "synthetic", n_textures=10, duration_s=4, image_size=256)


@pytest.fixture(scope="module")
def model(dataset, tmp_path_factory):
    return train_and_export(
        dataset, "ridge-tactile", tmp_path_factory.mktemp("m") / "ridge.onnx", seed=1, calibration_folds=5
    )


def test_card_carries_calibrations_for_every_target_and_a_detector(model):
    card = read_card(model)
    cals = calibrations_from_card(card.intervals)
    assert set(cals) == {"window", "ema", "texture"}
    assert cals["ema"].ema_alpha == 0.5 and cals["window"].n_textures == 10
    assert "5-fold CV over 10 training textures" in cals["window"].method
    det = OODDetector.from_dict(card.ood)
    assert det.n_tactile == Predictor(model).n_tactile and det.visual is None and det.n_textures == 10
    # a single window scatters more than a texture's mean: its interval is wider
    q_window, _ = cals["window"].quantile(0.9)
    q_texture, _ = cals["texture"].quantile(0.9)
    assert np.all(q_window > q_texture)


def test_serving_path_gives_intervals_and_flags_window_by_window(model, dataset):
    card = read_card(model)
    cals = calibrations_from_card(card.intervals)
    det = OODDetector.from_dict(card.ood)
    predictor = Predictor(model)
    data = load_texture_data(dataset, visual=False)
    windows = data.tactile[0][:6]
    raw = predictor.predict(windows)
    res = det.check(windows, None)
    lo, hi = cals["window"].interval(raw, None, level=0.9, ood=res.flags)
    assert lo.shape == hi.shape == (6, 4) and np.all(lo <= raw + 1e-6) and np.all(raw <= hi + 1e-6)
    fast = windows.copy()
    fast[:, -6:-3] *= 20  # speed statistics twenty times anything in training
    flagged = det.check(fast, None)
    assert flagged.flags.all() and all("speed_out_of_range" in r for r in flagged.reasons)
    lo_f, hi_f = cals["window"].interval(predictor.predict(fast), None, level=0.9, ood=flagged.flags)
    assert np.all(hi_f - lo_f >= 0.99 * (hi - lo).min())


def test_streaming_ema_state_equals_the_offline_definition():
    rng = np.random.default_rng(0)
    flags = rng.random(30) < 0.2
    dist = rng.uniform(0.5, 3, 30)
    state = EmaUncertainty(0.5)
    online = [state.update(bool(f), float(d)) for f, d in zip(flags, dist)]
    np.testing.assert_array_equal([o[0] for o in online], ema_flags(flags, 0.5))
    np.testing.assert_allclose([o[1] for o in online], ema(dist[:, None], 0.5)[:, 0])
    with pytest.raises(ValueError):
        state.update(True, 0.0)


def test_too_few_textures_train_without_intervals(tmp_path):
    small = build("synthetic", tmp_path / "small", n_textures=5, duration_s=3, image_size=256)
    with pytest.warns(UserWarning, match="too few"):
        path = train_and_export(small, "ridge-tactile", tmp_path / "m.onnx")
    card = read_card(path)
    assert card.intervals is None and card.ood is None
