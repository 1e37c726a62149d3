"""The operator's renderer: blocks of any size give the whole stroke's samples in all four dimensions (vibration, bumps,
taps, friction), the same filter as the world's `render` at a fixed operating point and without its turnaround
bursts, crossfaded switches, known answers for bumps and taps, the corner floor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.procedural import make_world
from texture_library.renderer import StreamRenderer, render_stroke, tap_transient
from texture_library.surface import SurfaceProfile
from texture_library.synthesis import corner_floor, render
from texture_library.vibration import VibrationModel


def _other(model: VibrationModel) -> VibrationModel:
    """Another texture on the same grid: a smooth hum (resonances at 30 and 80 Hz), four times the variance, μ 0.7."""
    ar = poly_to_lsf(poles_to_poly(np.array([30.0, 80.0]), np.array([0.97, 0.9]), 1000.0))
    return dataclasses.replace(
        model, name="other", ar_lsf=np.tile(ar, (model.speeds.size, 1)), variance=4 * model.variance, mu=0.7
    )


def _stroke(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / 1000.0
    return 100 + 90 * np.sin(2 * np.pi * 0.7 * t), 2 + 1.5 * np.cos(2 * np.pi * 0.3 * t)


@pytest.mark.parametrize("sizes", [(1,), (7, 20, 333, 1), (2000,)])
def test_blocks_equal_the_whole_stroke_sample_for_sample(sizes):
    """Vibration, bumps and taps (one tap overlapping the next, one across a block edge) carried across blocks."""
    model = make_world(7, 0, image_size=32)[6].model  # a synthetic texture with bumps and taps
    n = 2000
    speed, force = _stroke(n)
    position = np.cumsum(speed * np.sign(np.sin(np.arange(n) / 150.0) + 1e-9)) / 1000.0
    touchdown = np.zeros(n)
    touchdown[[5, 330, 340, 1999]] = [30.0, 12.5, 80.0, 5.0]
    e = np.random.default_rng(3).standard_normal(n)
    want = render_stroke(model, speed, force, excitation=e, position=position, touchdown=touchdown)
    r, got, i, k = StreamRenderer(model), [], 0, 0
    while i < n:
        b = sizes[k % len(sizes)]
        sl = slice(i, i + b)
        got.append(
            r.process(speed[sl], force[sl], excitation=e[sl], position=position[sl], touchdown=touchdown[sl]).accel
        )
        i, k = i + b, k + 1
    np.testing.assert_array_equal(np.concatenate(got), want)
    assert r.samples == n
    plain = render_stroke(model, speed, force, excitation=e)
    assert np.std(want - plain) > 0.1 * np.std(plain)  # bumps and taps are really there


def test_at_a_fixed_point_the_filter_is_the_worlds_render(model):
    """Poles first or direct form: the same filter while the coefficients hold still (equal to rounding)."""
    n = 3000
    e = np.random.default_rng(4).standard_normal(n)
    for speed, force in [(150.0, 3.0), (60.0, 1.0)]:
        want = render(model, np.full(n, speed), np.full(n, force), excitation=e)
        got = render_stroke(model, np.full(n, speed), np.full(n, force), excitation=e, floor=False)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


def test_a_turnaround_does_not_burst():
    """A back-and-forth stroke (159 → 0 → 159 mm/s): direct form I bursts far above the texture's steady level on
    synth_006; the operator's renderer stays at it. This test fails with the world's `render`."""
    model = make_world(7, 0, image_size=32)[6].model
    n = 1200
    phase = (np.arange(n) / 1000.0 % 0.8) / 0.8
    x = np.where(phase < 0.5, 2 * phase, 2 - 2 * phase) * 159.0 * 0.4
    speed = np.abs(np.gradient(x)) * 1000.0
    e = np.random.default_rng(0).standard_normal(n)
    steady = np.abs(render_stroke(model, np.full(n, 159.0), np.ones(n), excitation=e)).max()
    assert np.abs(render(model, speed, np.ones(n), excitation=e)).max() > 10 * steady  # the counterfactual
    assert np.abs(render_stroke(model, speed, np.ones(n), excitation=e)).max() <= 1.5 * steady


def test_its_own_rng_draws_what_render_draws(model):
    speed, force = _stroke(1000)
    r = StreamRenderer(model, np.random.default_rng(9))
    got = np.concatenate([r.process(speed[i : i + 50], force[i : i + 50]).accel for i in range(0, 1000, 50)])
    e = np.random.default_rng(9).standard_normal(1000)
    np.testing.assert_array_equal(got, render_stroke(model, speed, force, excitation=e))


def test_bumps_known_answer(model):
    """A bump train of height h and period P stroked at a steady v from rest: after the first two samples (at rest,
    then starting) the output is z''(x)·v² = −(h/2)(2π/P)²·cos(2πx/P)·v², a line at v/P Hz."""
    h, period, v, n = 0.8, 10.0, 120.0, 2000
    bumpy = dataclasses.replace(model, surface=SurfaceProfile(h, period), variance=np.zeros(model.speeds.size))
    x = 3.0 + v * np.arange(n) / 1000.0
    y = render_stroke(bumpy, np.full(n, v), np.full(n, 2.0), excitation=np.zeros(n), position=x)
    k = 2 * np.pi / period
    np.testing.assert_allclose(y[2:], -0.5 * h * k * k * np.cos(k * x[2:]) * v * v * 1e-3, rtol=1e-9)
    assert y[0] == 0.0  # at rest at the first position
    spectrum = np.abs(np.fft.rfft(y[2:1002]))
    assert np.argmax(spectrum) == round(v / period)  # 1 Hz bins over 1 s
    # without positions, or on a model without a profile: no bumps
    assert np.all(render_stroke(bumpy, np.full(n, v), np.full(n, 2.0), excitation=np.zeros(n)) == 0)
    assert np.all(render_stroke(model, np.full(n, v), np.full(n, 2.0), excitation=np.zeros(n), position=x) == 0)


def test_taps_known_answer(model_with_taps):
    """A touchdown plays the recorded tap nearest its speed (the first of equals), scaled by speed / recorded speed."""
    taps = model_with_taps.taps
    quiet = dataclasses.replace(model_with_taps, variance=np.zeros(model_with_taps.speeds.size))
    n = 400
    touchdown = np.zeros(n)
    touchdown[[10, 250]] = [20.0, 25.0]  # nearest 10 mm/s (×2); 25 is as near 10 as 40: the first, 10 (×2.5)
    y = render_stroke(quiet, np.zeros(n), np.ones(n), excitation=np.zeros(n), touchdown=touchdown)
    want = np.zeros(n)
    want[10:110] += 2.0 * taps.accel[0]
    want[250:350] += 2.5 * taps.accel[0]
    np.testing.assert_allclose(y, want, rtol=1e-12)
    np.testing.assert_array_equal(tap_transient(quiet, 40.0), taps.accel[1])
    assert tap_transient(quiet, 0.0).size == 0
    assert tap_transient(dataclasses.replace(quiet, taps=None), 40.0).size == 0
    # a faster touchdown, a larger transient: linear in the contact speed
    fast = render_stroke(quiet, np.zeros(n), np.ones(n), excitation=np.zeros(n), touchdown=np.eye(1, n, 10)[0] * 60.0)
    np.testing.assert_allclose(fast[10:110], 1.5 * taps.accel[1])


def test_corner_floor_keeps_a_slow_stroke_audible():
    """The synthetic world's cell below 87.5 mm/s and 1.25 N has three silent corners: a plain blend is silent at
    10 mm/s and 1 N; the floor plays v_r·(s/s_r)²·(f/f_r) there, and never binds where every corner vibrates."""
    model = make_world(8, 0, image_size=32)[7].model
    n = 2000
    e = np.random.default_rng(2).standard_normal(n)
    speed, force = np.full(n, 10.0), np.ones(n)
    assert np.all(render(model, speed, force, excitation=e) == 0)
    y = render_stroke(model, speed, force, excitation=e)
    positive = model.variance > 0
    k = np.flatnonzero(positive)[np.argmin(model.variance[positive])]
    want = model.variance[k] * (10.0 / model.speeds[k]) ** 2 * min(1.0, 1.0 / model.forces[k])
    np.testing.assert_allclose(corner_floor(model, np.array([10.0]), np.array([1.0])), [want])
    steady = render_stroke(model, speed, force, excitation=e, floor=False)
    assert np.all(steady == 0) and np.std(y[500:]) > 0
    # where every corner of the triangle vibrates the floor is below the blend: the same samples either way
    inside = (np.full(n, 200.0), np.full(n, 3.0))
    np.testing.assert_array_equal(
        render_stroke(model, *inside, excitation=e), render_stroke(model, *inside, excitation=e, floor=False)
    )


def _switch_run(a: VibrationModel, b: VibrationModel, at: int, crossfade_s: float, n: int = 3000):
    speed, force = np.full(n, 150.0), np.full(n, 3.0)
    e = np.random.default_rng(1).standard_normal(n)
    r, out, friction = StreamRenderer(a, crossfade_s=crossfade_s), [], []
    for i in range(0, n, 10):
        if i == at:
            r.switch(b)
        block = r.process(speed[i : i + 10], force[i : i + 10], excitation=e[i : i + 10])
        out.append(block.accel)
        friction.append(block.friction)
    alone = [StreamRenderer(m).process(speed, force, excitation=e).accel for m in (a, b)]
    return np.concatenate(out), np.concatenate(friction), alone


def test_a_switch_is_crossfaded_without_a_step_larger_than_the_signals_own(model):
    loud = _other(model)
    # From the loud hum to the quiet texture, where the hum is at its loudest: the worst moment for a hard cut.
    _, _, (ya, yb) = _switch_run(loud, model, 3000, 0.05)
    at = 1000 + 10 * (int(np.argmax(np.abs(ya[1000:1500]))) // 10)
    spread = max(np.abs(np.diff(y[200:])).max() for y in (ya, yb))  # each signal's own sample-to-sample spread

    y, friction, _ = _switch_run(loud, model, at, 0.05)
    assert np.abs(np.diff(y[200:])).max() <= spread * (1 + 1e-9)
    np.testing.assert_array_equal(y[:at], ya[:at])  # nothing changes before the switch
    assert np.allclose(friction[:at], 0.7 * 3.0) and np.allclose(friction[at + 50 :], 0.4 * 3.0)
    assert np.all(np.diff(friction) <= 1e-12)  # μ·F fades monotonically from 0.7·F to 0.4·F

    hard, _, _ = _switch_run(loud, model, at, 0.0)  # the same switch uncrossfaded clicks: this test can fail
    assert np.abs(np.diff(hard[200:])).max() > 1.5 * spread


def test_after_the_crossfade_only_the_new_model_plays(model):
    n, at = 3000, 1000
    e = np.random.default_rng(1).standard_normal(n)
    y, _, _ = _switch_run(model, _other(model), at, 0.05, n)
    # The new voice starts at rest at the switch: once the fade is over, the output is that voice alone.
    fresh = StreamRenderer(_other(model)).process(np.full(n - at, 150.0), np.full(n - at, 3.0), excitation=e[at:])
    np.testing.assert_array_equal(y[at + 50 :], fresh.accel[50:])


def test_friction_is_mu_times_the_normal_force(model):
    force = np.array([0.0, 1.0, 2.5, -1.0])
    block = StreamRenderer(model).process(np.full(4, 50.0), force)
    np.testing.assert_allclose(block.friction, [0.0, 0.4, 1.0, 0.0])


def test_bad_blocks_are_refused_with_the_reason(model):
    r = StreamRenderer(model)
    with pytest.raises(ValueError, match="equal length"):
        r.process(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        r.process(np.array([np.nan]), np.zeros(1))
    with pytest.raises(ValueError, match="excitation must have shape"):
        r.process(np.zeros(3), np.zeros(3), excitation=np.zeros(2))
    with pytest.raises(ValueError, match="position must have shape"):
        r.process(np.zeros(3), np.zeros(3), position=np.zeros(4))
    with pytest.raises(ValueError, match="touchdown must be finite"):
        r.process(np.zeros(3), np.zeros(3), touchdown=np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="crossfade_s"):
        StreamRenderer(model, crossfade_s=-1)
    with pytest.raises(ValueError, match="renders at"):
        r.switch(dataclasses.replace(model, rate_hz=2000.0))
    assert r.process(np.zeros(0), np.zeros(0)).accel.size == 0
