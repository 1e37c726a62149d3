"""When a session's learnt surface model (models.tactile.surface_fit) goes out to its operators, and what it holds.

**When.** A new version is published only when the fit would feel different from the last one sent (the gate,
below), at most once per MIN_INTERVAL_S, and only within the served size cap
(texture_library.render_model.MAX_RENDER_MODEL_BYTES):

  vibration  the mean log-spectral distance between the two models over the report's nine operating points
             (texture_library.spectrum.spectral_distance_db) is at least PERCEPTIBLE_DB — half the 2.2–2.5 dB
             amplitude difference people can just detect, so two unsent steps never add up to a felt jump;
  friction   |Δμ| at least MU_STEP;
  bumps      a profile appears or goes, or its height changes by PERCEPTIBLE_DB (20·log10) or its period by
             PERIOD_STEP;
  taps       taps appear where there were none.

**What, point by point.** A refit moves every grid point's LSFs by a few code steps, even where the spectrum
moved imperceptibly, so a version made of the whole fit costs a 300–600-byte delta on the wire. A published
version is therefore the last published model with only the perceptible moves taken from the fit (`merged`):

  grid point  the fit's row (AR and MA LSFs, variance, gain) where that point's spectrum (the ARMA model at the
              point itself, over the band of texture_library.spectrum) is at least POINT_DB from the published
              row's; the published row, exactly, elsewhere. POINT_DB = PERCEPTIBLE_DB / 2 = 0.5 dB (RMS dB over
              the band): right after a publication the operator's model is within 0.5 dB of the fit at every grid
              point, so the residue alone stays clear of the gate (a mean of 1 dB): about half of it must be new
              movement;
  friction    the published μ unless it moved by MU_STEP; bumps the published profile unless they moved
              perceptibly (as above); taps the fit's.

Kept rows are byte-identical in the codec (texture_library.model_codec), so the delta is zeros there and
deflates to little. A fit whose ARMA orders (or grid) differ from the published one's cannot keep rows: it goes
out whole, and so does one whose merged version the gate would still call perceptibly different from the fit
(small moves under POINT_DB at many points adding up, or the renderer's interpolation between kept and new rows):
the whole-model rule keeps its promise, the operator holds a model within PERCEPTIBLE_DB of the fit after every
publication, and within POINT_DB of it at every grid point whenever rows were kept.

Each published document is a `RenderModel` under the session's entry id; its `model_version` (the content's
hash) is what the choice event names and the ETag fetch serves.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from texture_library.render_model import RenderModel
from texture_library.spectrum import arma_psd, band_frequencies, log_spectral_distance_db, spectral_distance_db
from texture_library.vibration import VibrationModel

PERCEPTIBLE_DB = 1.0
MU_STEP = 0.05
PERIOD_STEP = 0.05
MIN_INTERVAL_S = 1.0
#: a grid point's new fit replaces its published row when their spectra at that point differ by this much (dB)
POINT_DB = PERCEPTIBLE_DB / 2


def perceptibly_different(old: VibrationModel, new: VibrationModel, threshold_db: float = PERCEPTIBLE_DB) -> str | None:
    """Why `new` would feel different from `old` (the first dimension that differs), or None."""
    if spectral_distance_db(old, new) >= threshold_db:
        return "vibration"
    if abs(new.mu - old.mu) >= MU_STEP:
        return "friction"
    if bumps_moved(old, new, threshold_db):
        return "bumps"
    if old.taps is None and new.taps is not None:
        return "taps"
    return None


def bumps_moved(old: VibrationModel, new: VibrationModel, threshold_db: float = PERCEPTIBLE_DB) -> bool:
    """A bump profile appears or goes, or its height changes by threshold_db (20·log10) or its period by
    PERIOD_STEP (relative)."""
    a, b = old.surface, new.surface
    if (a is None or a.bump_height_mm == 0) != (b is None or b.bump_height_mm == 0):
        return True
    if a is not None and b is not None and a.bump_height_mm > 0 and b.bump_height_mm > 0:
        if abs(20 * math.log10(b.bump_height_mm / a.bump_height_mm)) >= threshold_db:
            return True
        if abs(b.bump_period_mm / a.bump_period_mm - 1) >= PERIOD_STEP:
            return True
    return False


def point_distances_db(a: VibrationModel, b: VibrationModel) -> np.ndarray:
    """(m,) log-spectral distance, dB, between the two models' ARMA models at each of a's grid points (the RMS dB
    over texture_library.spectrum's band). The two must share the grid (ValueError otherwise)."""
    if not same_grid(a, b):
        raise ValueError("point distances need two models on the same grid (speeds, forces, triangles)")
    freqs = band_frequencies()
    return log_spectral_distance_db(arma_psd(a, a.speeds, a.forces, freqs), arma_psd(b, b.speeds, b.forces, freqs))


def same_grid(a: VibrationModel, b: VibrationModel) -> bool:
    """The two models' grids are the same points and triangles, and their ARMA orders agree (rows interchange)."""
    return bool(
        np.shape(a.speeds) == np.shape(b.speeds)
        and np.array_equal(a.speeds, b.speeds)
        and np.array_equal(a.forces, b.forces)
        and np.shape(a.triangles) == np.shape(b.triangles)
        and np.array_equal(a.triangles, b.triangles)
        and (a.ar_order, a.ma_order) == (b.ar_order, b.ma_order)
        and (a.max_speed, a.max_force, a.rate_hz) == (b.max_speed, b.max_force, b.rate_hz)
    )


def merged(published: VibrationModel, fit: VibrationModel, point_db: float = POINT_DB) -> VibrationModel:
    """The version to send for `fit` when the operators hold `published` (see the module docstring): the
    published rows, μ and bumps wherever the fit moved them imperceptibly, the fit's elsewhere; the fit itself
    when the two cannot share rows (another grid or ARMA orders). Name, taps, provenance and extra: the fit's."""
    if not same_grid(published, fit):
        return fit
    moved = point_distances_db(published, fit) >= point_db
    take = moved[:, None]
    mu = fit.mu if abs(fit.mu - published.mu) >= MU_STEP else published.mu
    surface = fit.surface if bumps_moved(published, fit, PERCEPTIBLE_DB) else published.surface
    return replace(
        fit,
        ar_lsf=np.where(take, fit.ar_lsf, published.ar_lsf),
        ma_lsf=np.where(take, fit.ma_lsf, published.ma_lsf),
        variance=np.where(moved, fit.variance, published.variance),
        gain=np.where(moved, fit.gain, published.gain),
        mu=mu,
        surface=surface,
    )


class SurfacePublisher:
    """Decides, offer by offer, whether a session's newest surface model is sent (see the module docstring).

    entry_id: the id its RenderModel documents carry; threshold_db: the gate (PERCEPTIBLE_DB), point_db: a grid
    point's (POINT_DB), both dB; `published`: versions sent so far; `last`: the model last sent (merged, not the
    fit); `last_refusal`: why the newest offer was not sent ("too soon", "imperceptible", or the size cap's
    message), None after a send.
    """

    def __init__(
        self,
        entry_id: str,
        threshold_db: float = PERCEPTIBLE_DB,
        min_interval_s: float = MIN_INTERVAL_S,
        point_db: float = POINT_DB,
    ) -> None:
        if not (math.isfinite(threshold_db) and threshold_db > 0):
            raise ValueError(f"threshold_db must be a finite number > 0, got {threshold_db}")
        if not (math.isfinite(point_db) and point_db > 0):
            raise ValueError(f"point_db must be a finite number > 0, got {point_db}")
        if not (math.isfinite(min_interval_s) and min_interval_s >= 0):
            raise ValueError(f"min_interval_s must be a finite number ≥ 0, got {min_interval_s}")
        self.entry_id = entry_id
        self.threshold_db = threshold_db
        self.min_interval_s = min_interval_s
        self.point_db = point_db
        self.published = 0
        self.last_refusal: str | None = None
        self._last: VibrationModel | None = None
        self._last_s = -math.inf

    @property
    def last(self) -> VibrationModel | None:
        return self._last

    def offer(self, model: VibrationModel, now_s: float) -> RenderModel | None:
        """The document to send for the fit `model` at time now_s (s, monotonic), or None (see last_refusal): the
        last published model with the fit's perceptible moves (`merged`), or the fit itself the first time."""
        if now_s - self._last_s < self.min_interval_s:
            self.last_refusal = "too soon"
            return None
        if self._last is not None and perceptibly_different(self._last, model, self.threshold_db) is None:
            self.last_refusal = "imperceptible"
            return None
        if self._last is not None:
            candidate = merged(self._last, model, self.point_db)
            if perceptibly_different(candidate, model, self.threshold_db) is not None:
                candidate = model  # the kept rows add up to a perceptible difference: the fit goes out whole
            model = candidate
        try:
            document = RenderModel.from_vibration_model(self.entry_id, model)
        except ValueError as exc:  # over the size cap: the operators keep the last version
            self.last_refusal = str(exc)
            return None
        self._last, self._last_s = model, now_s
        self.published += 1
        self.last_refusal = None
        return document
