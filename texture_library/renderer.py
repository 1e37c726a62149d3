"""The real-time renderer: a streaming, stateful ARMA vibration renderer driven block by block.

An operator's device reports its own speed (mm/s) and normal force (N) at the model's rate (1 kHz); each
block of those becomes a block of acceleration (m/s²) — the texture's vibration, exactly as
`texture_library.synthesis.render` would give for the whole trajectory at once: the same interpolation
(`synthesis.interpolate`) and the same ARMA loop (`synthesis.arma_filter`), carried across blocks by the
filter's history. Fed the same excitation, the two agree sample for sample.

A switch to another model (the service chose another library entry) is crossfaded: for `crossfade_s`
both models run on the same excitation and a raised-cosine gain hands the output from the old one to the
new one, so the switch never clicks. The friction force μ·F_normal (N) comes with every block, crossfaded
the same way, for a device that renders it.

What it does not render: a model's macro surface profile (bumps, `texture_library.stroke`), which needs
the tool's position, and tap transients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texture_library.synthesis import arma_filter, check_trajectory, interpolate
from texture_library.vibration import VibrationModel

#: default crossfade length on a model switch, s (50 ms: far shorter than a stroke, long enough not to click)
CROSSFADE_S = 0.05


@dataclass(frozen=True)
class RenderedBlock:
    """One block of output: accel (n,) m/s² (the vibration to play); friction (n,) N (μ·F_normal)."""

    accel: np.ndarray
    friction: np.ndarray


class _Voice:
    """One model's ARMA filter and its history between blocks."""

    def __init__(self, model: VibrationModel) -> None:
        self.model = model
        self.e_history = np.zeros(model.ma_order)
        self.y_history = np.zeros(model.ar_order)

    def render(self, speed: np.ndarray, force: np.ndarray, unit_excitation: np.ndarray) -> np.ndarray:
        params = interpolate(self.model, speed, force)
        e = unit_excitation * np.sqrt(params["variance"])
        y = arma_filter(params["ar"], params["ma"] * params["gain"][:, None], e, self.e_history, self.y_history)
        q, p = self.e_history.size, self.y_history.size
        if q:
            self.e_history = np.concatenate([self.e_history, e])[-q:]
        if p:
            self.y_history = np.concatenate([self.y_history, y])[-p:]
        return y


class StreamRenderer:
    """Renders a model block by block; `switch` crossfades to another.

    model: the model to start with; rng: where the unit-variance excitation comes from when a block brings
    none (one `standard_normal(n)` call per block, so one block of n samples draws what `render` draws);
    crossfade_s: how long a switch takes, s.
    """

    def __init__(
        self, model: VibrationModel, rng: np.random.Generator | None = None, *, crossfade_s: float = CROSSFADE_S
    ) -> None:
        if not crossfade_s >= 0:
            raise ValueError(f"crossfade_s must be ≥ 0, got {crossfade_s}")
        self.rng = rng if rng is not None else np.random.default_rng()
        self.rate_hz = float(model.rate_hz)
        self.fade_samples = int(round(crossfade_s * self.rate_hz))
        self._current = _Voice(model)
        self._leaving: _Voice | None = None
        self._fade_done = 0  # samples of the running crossfade already rendered
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
            self._current, self._leaving = _Voice(model), None
            return
        self._leaving, self._current = self._current, _Voice(model)
        self._fade_done = 0

    def process(self, speed: np.ndarray, force: np.ndarray, excitation: np.ndarray | None = None) -> RenderedBlock:
        """One block: speed (n,) mm/s and force (n,) N at rate_hz → RenderedBlock (n samples).

        excitation: (n,) unit-variance white noise to use instead of the renderer's rng (tests, replays).
        """
        speed, force = check_trajectory(speed, force)
        n = speed.size
        if excitation is None:
            excitation = self.rng.standard_normal(n)
        excitation = np.asarray(excitation, float)
        if excitation.shape != (n,):
            raise ValueError(f"excitation must have shape ({n},), got {excitation.shape}")
        self.samples += n
        if n == 0:
            return RenderedBlock(np.zeros(0), np.zeros(0))
        y = self._current.render(speed, force, excitation)
        friction = self._current.model.mu * np.clip(force, 0.0, None)
        if self._leaving is None:
            return RenderedBlock(y, friction)
        old = self._leaving.render(speed, force, excitation)
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
        return RenderedBlock(w * y + (1.0 - w) * old, w * friction + (1.0 - w) * old_friction)
