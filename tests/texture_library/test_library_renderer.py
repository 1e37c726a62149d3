"""The streaming renderer: sample-for-sample parity with the offline render, crossfaded switches, friction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.renderer import StreamRenderer
from texture_library.synthesis import render
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
def test_blocks_equal_the_offline_render_sample_for_sample(model, sizes):
    n = 2000
    speed, force = _stroke(n)
    e = np.random.default_rng(3).standard_normal(n)
    want = render(model, speed, force, excitation=e)
    r, got, i, k = StreamRenderer(model), [], 0, 0
    while i < n:
        b = sizes[k % len(sizes)]
        got.append(r.process(speed[i : i + b], force[i : i + b], excitation=e[i : i + b]).accel)
        i, k = i + b, k + 1
    np.testing.assert_array_equal(np.concatenate(got), want)
    assert r.samples == n


def test_its_own_rng_draws_what_render_draws(model):
    speed, force = _stroke(1000)
    r = StreamRenderer(model, np.random.default_rng(9))
    got = np.concatenate([r.process(speed[i : i + 50], force[i : i + 50]).accel for i in range(0, 1000, 50)])
    np.testing.assert_array_equal(got, render(model, speed, force, np.random.default_rng(9)))


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
    with pytest.raises(ValueError, match="crossfade_s"):
        StreamRenderer(model, crossfade_s=-1)
    with pytest.raises(ValueError, match="renders at"):
        r.switch(dataclasses.replace(model, rate_hz=2000.0))
    assert r.process(np.zeros(0), np.zeros(0)).accel.size == 0
