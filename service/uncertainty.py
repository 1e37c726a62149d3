"""What the service says about how far to trust a window: its interval and its out-of-distribution flag.

A served model's card may carry interval calibrations (`models.inference.intervals.IntervalCalibration`) and an
`models.inference.ood.OODDetector`, both written by `hapticlink train`. `ServedModel` is a loaded model with
them; `SessionUncertainty` is one session's running state. Per window:

    ood check     detector.check(the window's features, the frame's FrameCheck)   → flag, reasons, distance
    EMA state     EmaUncertainty: flag and distance smoothed exactly like the ratings
    interval      calibration.interval(smoothed ratings, √distance if normalised, level, ood=smoothed flag)

The interval is the one of the estimate the event shows, the EMA-smoothed `ratings`: the card's "ema"
calibration when its alpha equals the service's smoothing alpha, else (or with alpha 1, no smoothing)
its "window" calibration, whose band is calibrated for a single window's raw estimate (smoothing only
averages window noise away, so it covers the smoothed estimate at least as often). A model without a
calibration gets no interval (`None`: never a made-up one); a model without a detector gets no flag
(`None`). Numpy only; a few tens of µs per window (`python -m benchmarks.uncertainty`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.inference.intervals import EmaUncertainty, IntervalCalibration, calibrations_from_card
from models.inference.ood import FrameCheck, OODDetector, OODResult
from models.inference.predictor import Predictor

#: the reason a clean window of a smoothed estimate still carries when earlier flagged windows taint its EMA
RECENT_FLAGGED = "recent_window_flagged"
#: the smoothed estimate's interval is its own ("ema") calibration's once the EMA's noise variance is within this
#: factor of its steady state; before that (the session's first windows) the single window's band serves
SETTLED_VARIANCE_RATIO = 1.25


def ema_variance_ratio(alpha: float, n: int) -> float:
    """Noise variance of an EMA (s_1 = x_1, s_k = α·x_k + (1 − α)·s_(k−1)) after n ≥ 1 windows of independent noise,
    over its steady state α / (2 − α): 1/(α/(2 − α)) at n = 1, falling to 1."""
    if not 0 < alpha <= 1 or n < 1:
        raise ValueError(f"alpha must lie in (0, 1] and n ≥ 1, got {alpha}, {n}")
    q = (1.0 - alpha) ** 2
    variance = q ** (n - 1) + alpha**2 * (1.0 - q ** (n - 1)) / (1.0 - q) if q < 1 else 1.0
    return variance / (alpha / (2.0 - alpha))


@dataclass(frozen=True)
class Interval:
    """lo, hi: (A,) bipolar; level: nominal coverage; target: the calibration used ("ema" | "window")."""

    lo: np.ndarray
    hi: np.ndarray
    level: float
    target: str


@dataclass(frozen=True)
class Assessment:
    """One window's uncertainty as published: interval (None: the model carries no calibration);
    out_of_distribution (None: the model carries no detector); ood_reasons: sorted reasons; provisional: the
    smoothed estimate rests on too few windows for its own calibration (the interval is the single window's)."""

    interval: Interval | None
    out_of_distribution: bool | None
    ood_reasons: tuple[str, ...]
    provisional: bool = False


@dataclass(frozen=True)
class ServedModel:
    """A loaded model with its card's uncertainty: the calibration of the smoothed estimate (see the module
    docstring), the per-window ("window") calibration the adaptive policy reads, and the detector."""

    predictor: Predictor
    calibration: IntervalCalibration | None
    window_calibration: IntervalCalibration | None
    detector: OODDetector | None

    @classmethod
    def load(cls, predictor: Predictor, smoothing_alpha: float) -> ServedModel:
        """ValueError if the card's calibrations or detector cannot be read, or do not fit the model's inputs."""
        card = predictor.card
        try:
            cals = calibrations_from_card(card.intervals)
            detector = None if card.ood is None else OODDetector.from_dict(card.ood)
        except ValueError as exc:
            raise ValueError(f"{predictor.path}: unreadable uncertainty in its card ({exc})") from None
        if detector is not None and predictor.needs_tactile and detector.n_tactile != predictor.n_tactile:
            raise ValueError(
                f"{predictor.path}: its OOD detector reads {detector.n_tactile} tactile features, the model "
                f"{predictor.n_tactile}"
            )
        if detector is not None and detector.visual is not None and detector.n_visual != predictor.n_visual:
            raise ValueError(
                f"{predictor.path}: its OOD detector reads {detector.n_visual} visual features, the model "
                f"{predictor.n_visual}"
            )
        ema = cals.get("ema")
        smoothed = (
            ema
            if (
                ema is not None
                and smoothing_alpha < 1
                and ema.ema_alpha is not None
                and abs(ema.ema_alpha - smoothing_alpha) < 1e-9
            )
            else cals.get("window")
        )
        return cls(predictor, smoothed, cals.get("window"), detector)

    @property
    def name(self) -> str:
        return self.predictor.card.model

    def frame_reasons(self, gray: np.ndarray) -> list[str]:
        """Once per embedded frame (visual pool, ≈ 1 ms): why the frame (H, W) in [0, 1] looks unlike the training
        photos, by this model's detector (empty: fine, or no detector)."""
        return [] if self.detector is None else self.detector.check_frame(gray)

    def frame_check(self, reasons: list[str], visual: np.ndarray) -> FrameCheck | None:
        """The session's visual input (D,) and its frame's reasons → the FrameCheck every window of the scene
        shares (None without a detector)."""
        if self.detector is None:
            return None
        return self.detector.check_visual(visual if self.detector.visual is not None else None, reasons)

    def check(self, features: np.ndarray, frame: FrameCheck | None) -> OODResult | None:
        """features: (n, F) the windows' tactile features; frame: this model's FrameCheck of the session's
        current frame (None: no frame). None when the model carries no detector."""
        if self.detector is None:
            return None
        if frame is None:
            frame = self.detector.check_visual(None)
        return self.detector.check(features, frame=frame)

    def window_width(
        self, raw: np.ndarray, flagged: np.ndarray | None, distance: np.ndarray | None, level: float
    ) -> np.ndarray | None:
        """(n, A) width of each raw window estimate's interval (None without a window calibration).
        raw: (n, A); flagged, distance: (n,) the windows' checks (None: no detector)."""
        cal = self.window_calibration
        if cal is None:
            return None
        scale = None if cal.scale == "none" else (np.sqrt(distance) if distance is not None else np.ones(len(raw)))
        lo, hi = cal.interval(raw, scale, level, ood=flagged)
        return hi - lo


@dataclass
class SessionUncertainty:
    """One session's running uncertainty state (the flag and distance smoothed like the ratings)."""

    alpha: float
    level: float
    _ema: EmaUncertainty = field(init=False)
    _reasons: tuple[str, ...] = field(init=False, default=())
    _windows: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        if not 0 < self.level < 1:
            raise ValueError(f"interval level must lie in (0, 1), got {self.level}")
        self._ema = EmaUncertainty(self.alpha)

    def update(
        self,
        model: ServedModel,
        smoothed: np.ndarray,
        flagged: bool | None,
        reasons: list[str] | None,
        distance: float | None,
    ) -> Assessment:
        """One window, in order: the model that produced its raw estimate, the smoothed ratings (4,), and the
        window's own check (None without a detector)."""
        if flagged is None or distance is None:
            out: tuple[str, ...] = ()
            flag_s, dist_s = self._ema.update(False)[0], 1.0
            ood_flag: bool | None = None
        else:
            flag_s, dist_s = self._ema.update(bool(flagged), float(distance))
            if flagged:
                self._reasons = tuple(sorted(reasons or ()))
            out = tuple(sorted(reasons or ())) if flagged else ((RECENT_FLAGGED,) + self._reasons if flag_s else ())
            ood_flag = bool(flag_s)
        self._windows += 1
        # an EMA of one or two windows is as noisy as a single window: its steady-state band would under-cover it
        provisional = self.alpha < 1 and ema_variance_ratio(self.alpha, self._windows) > SETTLED_VARIANCE_RATIO
        cal = model.calibration
        if provisional and model.window_calibration is not None:
            cal = model.window_calibration
        if cal is None:
            return Assessment(None, ood_flag, out, provisional)
        scale = None if cal.scale == "none" else np.array([np.sqrt(dist_s)])
        lo, hi = cal.interval(smoothed[None, :], scale, self.level, ood=np.array([bool(flag_s)]))
        return Assessment(Interval(lo[0], hi[0], self.level, cal.target), ood_flag, out, provisional)
