"""When a session's learnt surface model (models.tactile.surface_fit) goes out to its operators.

A new version is published only when it would feel different from the last one sent, at most once per
MIN_INTERVAL_S, and only within the served size cap (texture_library.render_model.MAX_RENDER_MODEL_BYTES):

  vibration  the mean log-spectral distance between the two models over the report's nine operating points
             (texture_library.spectrum.spectral_distance_db) is at least PERCEPTIBLE_DB — half the 2.2–2.5 dB
             amplitude difference people can just detect, so two unsent steps never add up to a felt jump;
  friction   |Δμ| at least MU_STEP;
  bumps      a profile appears or goes, or its height changes by PERCEPTIBLE_DB (20·log10) or its period by
             PERIOD_STEP;
  taps       taps appear where there were none.

Each published document is a `RenderModel` under the session's entry id; its `model_version` (the content's
hash) is what the choice event names and the ETag fetch serves.
"""

from __future__ import annotations

import math

from texture_library.render_model import RenderModel
from texture_library.spectrum import spectral_distance_db
from texture_library.vibration import VibrationModel

PERCEPTIBLE_DB = 1.0
MU_STEP = 0.05
PERIOD_STEP = 0.05
MIN_INTERVAL_S = 1.0


def perceptibly_different(old: VibrationModel, new: VibrationModel, threshold_db: float = PERCEPTIBLE_DB) -> str | None:
    """Why `new` would feel different from `old` (the first dimension that differs), or None."""
    if spectral_distance_db(old, new) >= threshold_db:
        return "vibration"
    if abs(new.mu - old.mu) >= MU_STEP:
        return "friction"
    a, b = old.surface, new.surface
    if (a is None or a.bump_height_mm == 0) != (b is None or b.bump_height_mm == 0):
        return "bumps"
    if a is not None and b is not None and a.bump_height_mm > 0 and b.bump_height_mm > 0:
        if abs(20 * math.log10(b.bump_height_mm / a.bump_height_mm)) >= threshold_db:
            return "bumps"
        if abs(b.bump_period_mm / a.bump_period_mm - 1) >= PERIOD_STEP:
            return "bumps"
    if old.taps is None and new.taps is not None:
        return "taps"
    return None


class SurfacePublisher:
    """Decides, offer by offer, whether a session's newest surface model is sent (see the module docstring).

    entry_id: the id its RenderModel documents carry; `published`: versions sent so far; `last_refusal`: why the
    newest offer was not sent ("too soon", "imperceptible", or the size cap's message), None after a send.
    """

    def __init__(
        self, entry_id: str, threshold_db: float = PERCEPTIBLE_DB, min_interval_s: float = MIN_INTERVAL_S
    ) -> None:
        if not (math.isfinite(threshold_db) and threshold_db > 0):
            raise ValueError(f"threshold_db must be a finite number > 0, got {threshold_db}")
        if not (math.isfinite(min_interval_s) and min_interval_s >= 0):
            raise ValueError(f"min_interval_s must be a finite number ≥ 0, got {min_interval_s}")
        self.entry_id = entry_id
        self.threshold_db = threshold_db
        self.min_interval_s = min_interval_s
        self.published = 0
        self.last_refusal: str | None = None
        self._last: VibrationModel | None = None
        self._last_s = -math.inf

    def offer(self, model: VibrationModel, now_s: float) -> RenderModel | None:
        """The document to send for `model` at time now_s (s, monotonic), or None (see last_refusal)."""
        if now_s - self._last_s < self.min_interval_s:
            self.last_refusal = "too soon"
            return None
        if self._last is not None and perceptibly_different(self._last, model, self.threshold_db) is None:
            self.last_refusal = "imperceptible"
            return None
        try:
            document = RenderModel.from_vibration_model(self.entry_id, model)
        except ValueError as exc:  # over the size cap: the operators keep the last version
            self.last_refusal = str(exc)
            return None
        self._last, self._last_s = model, now_s
        self.published += 1
        self.last_refusal = None
        return document
