"""The real-time renderer: the operator's texture, in all four dimensions, block by block.

An operator's device reports its own speed (mm/s) and normal force (N) at the model's rate (1 kHz), and where it
can, its position along the surface (mm) and the speed at which it touches down (mm/s). Each block of those
becomes a block of acceleration (m/s²) and friction force (N):

- vibration (rough–smooth): the texture's ARMA model with `texture_library.synthesis.render`'s interpolation
  (`synthesis.interpolate`), the variance held at or above `synthesis.corner_floor` (a grid corner whose three
  points are silent does not silence a stroke; `floor=False` leaves it), run poles first (`arma_poles_first`:
  w = e / A, then y = B·w) where `render` runs direct form I (y[n] = B·e − Σ a·y). The two are the same filter
  at a fixed operating point (equal to rounding); they part where the coefficients move fast. Direct form I
  adds the change of the AR coefficients times the output history straight onto the output, where the AR
  part's gain near DC (≈ 7,000 for the synthetic world's 20 Hz high-pass) meets no MA zero to cancel it: at a
  mouse stroke's turnaround (159 → 0 → 159 mm/s in 0.1 s) 10 of the synthetic world's 24 textures burst to
  4–75× their steady level (synth_006: 349 m/s² against 4.6). Poles first, the change enters before the MA
  zeros and the bursts are gone (4.6 m/s²);
- bumps (flat–bumpy): where the model has a surface profile and the block brings positions, the profile's
  z''(x)·v² + z'(x)·v̇ (`SurfaceProfile.accel_at`, the formula the robot's stroke uses) at the operator's own
  position, with v and v̇ taken by backward differences carried across blocks (at the first position the
  tool is at rest);
- taps (hard–soft): at a sample where the tool touches down (`touchdown` > 0, the contact speed in mm/s), the
  model's recorded tap transient nearest that speed (the first of equals), scaled by contact speed / its
  recorded speed, as HaTT renders taps; it plays out whole, summed over overlapping taps;
- friction (sticky–slippery): μ·F_normal.

`render_stroke` renders a whole trajectory in one call; fed the same excitation, blocks of any size give the
same samples. A switch to another model (the service chose another library entry) is crossfaded: for
`crossfade_s` both models run on the same excitation and a raised-cosine gain hands vibration, bumps and
friction from the old one to the new one, so the switch never clicks; a tap already playing plays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from texture_library.synthesis import check_trajectory, interpolate
from texture_library.taps import TAP_RATE_HZ
from texture_library.vibration import VibrationModel

#: default crossfade length on a model switch, s (50 ms: far shorter than a stroke, long enough not to click)
CROSSFADE_S = 0.05


@dataclass(frozen=True)
class RenderedBlock:
    """One block of output: accel (n,) m/s² (vibration + bumps + taps, to play); friction (n,) N (μ·F_normal)."""

    accel: np.ndarray
    friction: np.ndarray


def tap_transient(model: VibrationModel, contact_speed: float) -> np.ndarray:
    """The tap played when the tool touches `model`'s surface at contact_speed mm/s: (k,) m/s² at the model's rate.

    The recorded tap whose speed is nearest (the first of equals), scaled by contact_speed / its speed (HaTT's
    rule: a tap's transient grows in proportion to the speed it comes in at). Empty when the model has no taps,
    when its taps are at another rate than the model renders at, or when contact_speed ≤ 0."""
    taps = model.taps
    if taps is None or not contact_speed > 0 or model.rate_hz != TAP_RATE_HZ:
        return np.zeros(0)
    speeds = np.asarray(taps.speeds, float)
    k = int(np.argmin(np.abs(speeds - contact_speed)))
    scale = contact_speed / speeds[k] if speeds[k] > 0 else 1.0
    return scale * np.asarray(taps.accel[k], float)


@numba.njit(cache=True)
def arma_poles_first(
    ar: np.ndarray, ma: np.ndarray, excitation: np.ndarray, w_history: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Time-varying ARMA, poles first: w[n] = e[n] − Σᵢ₌₁ ar[n,i]·w[n−i], then y[n] = Σⱼ ma[n,j]·w[n−j].

    ar: (n, p+1) monic AR coefficients; ma: (n, q+1) MA coefficients already scaled by the gain; excitation: (n,)
    e, already scaled by √variance; w_history: (L,) the L ≥ max(p, q) values of w before this block, oldest
    first (zeros: at rest). Returns (y (n,), the new w history (L,)). The browser's renderer runs the same loop."""
    n = excitation.shape[0]
    p = ar.shape[1] - 1
    q = ma.shape[1] - 1
    size = w_history.shape[0]
    w = np.empty(size + n)
    w[:size] = w_history
    y = np.empty(n)
    for t in range(n):
        acc = excitation[t]
        for i in range(1, p + 1):
            acc -= ar[t, i] * w[size + t - i]
        w[size + t] = acc
        out = 0.0
        for j in range(q + 1):
            out += ma[t, j] * w[size + t - j]
        y[t] = out
    return y, w[n:].copy()


class _Voice:
    """One model's ARMA filter (poles first) and its history between blocks."""

    def __init__(self, model: VibrationModel, floor: bool) -> None:
        self.model = model
        self.floor = floor
        self.w_history = np.zeros(max(model.ar_order, model.ma_order, 1))

    def render(self, speed: np.ndarray, force: np.ndarray, unit_excitation: np.ndarray) -> np.ndarray:
        params = interpolate(self.model, speed, force, floor=self.floor)
        e = unit_excitation * np.sqrt(params["variance"])
        y, self.w_history = arma_poles_first(params["ar"], params["ma"] * params["gain"][:, None], e, self.w_history)
        return y


class _Motion:
    """Velocity (mm/s) and its derivative (mm/s²) from positions by backward differences, across blocks."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz
        self.last: tuple[float, float] | None = None  # (position mm, velocity mm/s) of the sample before

    def differentiate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if x.size == 0:
            return np.zeros(0), np.zeros(0)
        x0, v0 = self.last if self.last is not None else (float(x[0]), 0.0)
        v = np.diff(x, prepend=x0) * self.rate_hz
        dv = np.diff(v, prepend=v0) * self.rate_hz
        self.last = (float(x[-1]), float(v[-1]))
        return v, dv


def _bumps(model: VibrationModel, x: np.ndarray | None, v: np.ndarray, dv: np.ndarray) -> np.ndarray | None:
    if model.surface is None or x is None:
        return None
    return model.surface.accel_at(x, v, dv)


class StreamRenderer:
    """Renders a model block by block; `switch` crossfades to another.

    model: the model to start with; rng: where the unit-variance excitation comes from when a block brings
    none (one `standard_normal(n)` call per block, so one block of n samples draws what `render` draws);
    crossfade_s: how long a switch takes, s; floor: hold the variance at or above `synthesis.corner_floor`.
    """

    def __init__(
        self,
        model: VibrationModel,
        rng: np.random.Generator | None = None,
        *,
        crossfade_s: float = CROSSFADE_S,
        floor: bool = True,
    ) -> None:
        if not crossfade_s >= 0:
            raise ValueError(f"crossfade_s must be ≥ 0, got {crossfade_s}")
        self.rng = rng if rng is not None else np.random.default_rng()
        self.rate_hz = float(model.rate_hz)
        self.fade_samples = int(round(crossfade_s * self.rate_hz))
        self.floor = floor
        self._current = _Voice(model, floor)
        self._leaving: _Voice | None = None
        self._fade_done = 0  # samples of the running crossfade already rendered
        self._motion = _Motion(self.rate_hz)
        self._taps: list[np.ndarray] = []  # what is left to play of each sounding tap
        self.samples = 0  # samples rendered since the start

    @property
    def model(self) -> VibrationModel:
        """The model being rendered (the new one from the moment of a switch)."""
        return self._current.model

    @property
    def crossfading(self) -> bool:
        return self._leaving is not None

    def switch(self, model: VibrationModel) -> None:
        """Crossfade to `model` from the next sample on. A switch during a crossfade starts a new one from what
        is playing now (the older voice is dropped, its share already faded below the new one's)."""
        if model.rate_hz != self.rate_hz:
            raise ValueError(f"model {model.name!r} renders at {model.rate_hz:g} Hz, this renderer at {self.rate_hz:g}")
        if model is self._current.model:
            return
        if self.fade_samples == 0:
            self._current, self._leaving = _Voice(model, self.floor), None
            return
        self._leaving, self._current = self._current, _Voice(model, self.floor)
        self._fade_done = 0

    def process(
        self,
        speed: np.ndarray,
        force: np.ndarray,
        excitation: np.ndarray | None = None,
        *,
        position: np.ndarray | None = None,
        touchdown: np.ndarray | None = None,
    ) -> RenderedBlock:
        """One block: speed (n,) mm/s and force (n,) N at rate_hz → RenderedBlock (n samples).

        excitation: (n,) unit-variance white noise to use instead of the renderer's rng (tests, replays);
        position: (n,) mm, the operator's position along the surface (bumps; None: a device without position
        renders none, and the next block with positions starts at rest); touchdown: (n,) mm/s, the contact speed
        at each sample where the tool touches the surface, 0 elsewhere (taps; None: none).
        """
        speed, force = check_trajectory(speed, force)
        n = speed.size
        if excitation is None:
            excitation = self.rng.standard_normal(n)
        excitation = np.asarray(excitation, float)
        if excitation.shape != (n,):
            raise ValueError(f"excitation must have shape ({n},), got {excitation.shape}")
        x = _optional("position", position, n)
        touch = _optional("touchdown", touchdown, n)
        self.samples += n
        if n == 0:
            return RenderedBlock(np.zeros(0), np.zeros(0))
        if x is None:
            self._motion.last = None
            v = dv = np.zeros(n)
        else:
            v, dv = self._motion.differentiate(x)
        y = self._current.render(speed, force, excitation)
        bumps = _bumps(self._current.model, x, v, dv)
        if bumps is not None:
            y = y + bumps
        friction = self._current.model.mu * np.clip(force, 0.0, None)
        if self._leaving is not None:
            old = self._leaving.render(speed, force, excitation)
            old_bumps = _bumps(self._leaving.model, x, v, dv)
            if old_bumps is not None:
                old = old + old_bumps
            old_friction = self._leaving.model.mu * np.clip(force, 0.0, None)
            k = self._fade_done + 1 + np.arange(n)
            w = np.where(
                k >= self.fade_samples,
                1.0,
                0.5 - 0.5 * np.cos(np.pi * np.minimum(k, self.fade_samples) / self.fade_samples),
            )
            self._fade_done += n
            if self._fade_done >= self.fade_samples:
                self._leaving = None
            y = w * y + (1.0 - w) * old
            friction = w * friction + (1.0 - w) * old_friction
        return RenderedBlock(self._play_taps(y, touch), friction)

    def _play_taps(self, y: np.ndarray, touch: np.ndarray | None) -> np.ndarray:
        """y plus what sounds of the taps already playing and those starting in this block."""
        n = y.size
        if touch is not None:
            for i in np.flatnonzero(touch > 0):
                transient = tap_transient(self._current.model, float(touch[i]))
                if transient.size:
                    self._taps.append(np.concatenate([np.zeros(i), transient]))
        if not self._taps:
            return y
        y = y.copy()
        left = []
        for tap in self._taps:
            y[: min(n, tap.size)] += tap[:n]
            if tap.size > n:
                left.append(tap[n:])
        self._taps = left
        return y


def _optional(name: str, values: np.ndarray | None, n: int) -> np.ndarray | None:
    if values is None:
        return None
    arr = np.asarray(values, float)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (no NaN/Inf)")
    return arr


def render_stroke(
    model: VibrationModel,
    speed: np.ndarray,
    force: np.ndarray,
    *,
    excitation: np.ndarray,
    position: np.ndarray | None = None,
    touchdown: np.ndarray | None = None,
    floor: bool = True,
) -> np.ndarray:
    """A whole operator stroke at once (what `StreamRenderer.process` gives in one block): accel (n,) m/s²."""
    r = StreamRenderer(model, floor=floor)
    return r.process(speed, force, excitation, position=position, touchdown=touchdown).accel
