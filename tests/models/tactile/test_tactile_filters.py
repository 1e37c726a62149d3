import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from models.tactile.filters import StatefulSOS, design_highpass, design_lowpass


def gain_db(sos, f, fs=1000.0):
    _, h = signal.sosfreqz(sos, worN=[f], fs=fs)
    return 20 * np.log10(np.abs(h[0]))


def test_accel_highpass_gain():
    sos = design_highpass(20.0, 1000.0, 4)
    assert gain_db(sos, 20.0) == pytest.approx(-3.01, abs=0.05)
    assert gain_db(sos, 100.0) >= -0.5
    assert gain_db(sos, 499.0) >= -0.01
    assert gain_db(sos, 2.0) <= -70.0


def test_lowpass_gain():
    sos = design_lowpass(25.0, 1000.0, 2)
    assert gain_db(sos, 25.0) == pytest.approx(-3.01, abs=0.05)
    assert gain_db(sos, 5.0) >= -0.05
    assert gain_db(sos, 250.0) <= -35.0


@pytest.mark.parametrize(
    "sos", [design_highpass(20.0, 1000.0, 4), design_lowpass(25.0, 1000.0, 2), design_highpass(1.0, 100_000.0, 8)]
)
def test_designs_are_stable(sos):
    _, poles, _ = signal.sos2zpk(sos)
    assert np.all(np.abs(poles) < 1)


def test_highpass_on_sines():
    t = np.arange(4000) / 1000.0
    sos = design_highpass(20.0, 1000.0, 4)
    y100 = StatefulSOS(sos).process(np.sin(2 * np.pi * 100 * t))[1000:]
    y2 = StatefulSOS(sos).process(np.sin(2 * np.pi * 2 * t))[1000:]
    assert np.sqrt(np.mean(y100**2)) == pytest.approx(np.sqrt(0.5), rel=0.01)
    assert np.max(np.abs(y2)) < 1e-3


@settings(max_examples=25, deadline=None)
@given(
    cuts=st.lists(st.integers(0, 300), min_size=0, max_size=6),
    cols=st.sampled_from([0, 1, 3]),
    init=st.sampled_from(["zero", "steady"]),
)
def test_chunked_equals_one_shot(cuts, cols, init):
    rng = np.random.default_rng(1)
    x = rng.standard_normal((300,) if cols == 0 else (300, cols)) + 3.0
    sos = design_highpass(20.0, 1000.0, 4)
    zi = None
    if init == "steady":
        x2 = x[:, None] if x.ndim == 1 else x
        zi = signal.sosfilt_zi(sos)[:, :, None] * x2[0][None, None, :]
    ref = signal.sosfilt(sos, x if x.ndim == 2 else x[:, None], axis=0, zi=zi)
    ref = (ref[0] if zi is not None else ref).reshape(x.shape)
    f = StatefulSOS(sos, init=init)
    pieces = np.split(x, sorted(cuts))
    out = np.concatenate([f.process(p) for p in pieces])
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


def test_steady_start_has_no_step():
    y = StatefulSOS(design_highpass(20.0, 1000.0, 4), init="steady").process(np.full(200, 9.81))
    assert np.max(np.abs(y)) < 1e-9


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((500.0, 1000.0, 4), "cutoff_hz"),
        ((0.0, 1000.0, 4), "cutoff_hz"),
        ((20.0, 0.0, 4), "rate_hz"),
        ((20.0, float("nan"), 4), "rate_hz"),
        ((20.0, 1000.0, 0), "order"),
    ],
)
def test_bad_designs(args, message):
    with pytest.raises(ValueError, match=message):
        design_highpass(*args)
    with pytest.raises(ValueError, match=message):
        design_lowpass(*args)


def test_stateful_rejects_bad_shapes():
    with pytest.raises(ValueError, match="sos"):
        StatefulSOS(np.ones((2, 5)))
    f = StatefulSOS(design_lowpass(25.0, 1000.0, 2))
    f.process(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="first block"):
        f.process(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="shape"):
        StatefulSOS(design_lowpass(25.0, 1000.0, 2)).process(np.zeros((2, 2, 2)))


@pytest.mark.parametrize("kernel", ["compiled", "public"])
def test_blocks_match_scipy_sosfilt_exactly(kernel, monkeypatch):
    # the compiled kernel is scipy's own, behind signal.sosfilt: the same numbers to the bit, either way
    if kernel == "public":
        monkeypatch.setattr("models.tactile.filters._sos_kernel", None)
    rng = np.random.default_rng(3)
    x = rng.standard_normal((700, 3)) + np.array([9.81, 0.0, -1.0])
    sos = design_highpass(20.0, 1000.0, 4)
    zi = signal.sosfilt_zi(sos)[:, :, None] * x[0][None, None, :]
    ref, _ = signal.sosfilt(sos, x, axis=0, zi=zi)
    f = StatefulSOS(sos, init="steady")
    out = np.concatenate([f.process(x[:100]), f.process(x[100:101]), f.process(x[101:])])
    np.testing.assert_array_equal(out, ref)
    one = StatefulSOS(sos, init="steady")
    np.testing.assert_array_equal(np.concatenate([one.process(x[:250, 0]), one.process(x[250:, 0])]), ref[:, 0])


def test_stateful_rejects_unnormalised_sections():
    sos = design_lowpass(25.0, 1000.0, 2)
    sos[0] *= 2.0  # a0 = 2: the kernel assumes every section divided through by a0
    with pytest.raises(ValueError, match="a0"):
        StatefulSOS(sos)
