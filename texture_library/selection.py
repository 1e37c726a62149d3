"""Which library entry to render: selection rules, the window's spectral match, and hysteresis.

Rules (written down, with how the hybrid's weight is tuned, in docs/models.md, fidelity section):
  perceptual    the entry nearest to the estimated ratings (`texture_library.nearest.PerceptualIndex`)
  physical      the entry under which the window's measured acceleration is most likely at the window's
                own speed and force: the Whittle (frequency-domain) approximation of the Gaussian ARMA
                likelihood over the band, as a mismatch in dB (`whittle_mismatch_db`)
  physical-lsd  the nearest spectral match: RMS dB between the window's spectrum and the entry's
  hybrid        d_rating + weight · whittle mismatch (dB)

The library's exact ARMA spectra are precomputed on a speed–force grid when the library is loaded
(`SpectralTable`): a window then costs one Welch spectrum and one bilinear read of the table, far
inside the per-window budget. `HysteresisChooser` keeps the rendered entry from flickering: a
challenger must be cheaper by `margin` (in the rule's units) for `hold` windows in a row.
"""

from __future__ import annotations

import bisect
import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.signal import get_window

from texture_library.spectrum import BAND_HZ, arma_psd
from texture_library.stroke import stroke
from texture_library.vibration import VibrationModel

RULES = ("perceptual", "physical", "physical-lsd", "hybrid")
#: Welch segment length at 1 kHz (7.8 Hz bins; a 500 ms window gives 6 half-overlapping segments)
WELCH_SEGMENT = 128
#: the service's accelerometer high-pass (models.tactile TactileConfig: 20 Hz, Butterworth order 4, one pass)
HIGHPASS_HZ = 20.0
HIGHPASS_ORDER = 4
#: per-axis white noise of the simulated robot's accelerometer, m/s² RMS (texture_library.stroke's default)
SIMULATED_SENSOR_NOISE = float(inspect.signature(stroke).parameters["noise_std"].default)
_LN10 = float(np.log(10.0))
_DB = 10.0 / _LN10
_FLOOR = 1e-12  # (m/s²)²/Hz under a spectrum before a log or a ratio


def band_mask(freqs_hz: np.ndarray, band_hz: tuple[float, float] = BAND_HZ) -> np.ndarray:
    """(n,) bool: bins inside [low, high) — the Nyquist bin of a one-sided Welch spectrum is left out."""
    f = np.asarray(freqs_hz, float)
    return (f >= band_hz[0]) & (f < band_hz[1])


def welch_frequencies(rate_hz: float = 1000.0, segment: int = WELCH_SEGMENT) -> np.ndarray:
    """(segment // 2 + 1,) the Welch bins, Hz."""
    return np.fft.rfftfreq(segment, 1.0 / rate_hz)


def sensor_noise_psd(noise_std: float, axes: int = 3, rate_hz: float = 1000.0) -> float:
    """One-sided PSD, (m/s²)²/Hz, of white sensor noise of `noise_std` m/s² RMS per axis, the axes summed."""
    if not (np.isfinite(noise_std) and noise_std >= 0) or axes < 1 or not rate_hz > 0:
        raise ValueError(f"noise_std must be finite and ≥ 0, axes ≥ 1, rate_hz > 0; got {noise_std}, {axes}, {rate_hz}")
    return axes * 2.0 * noise_std**2 / rate_hz


def window_psd(accel: np.ndarray, rate_hz: float = 1000.0, segment: int = WELCH_SEGMENT) -> np.ndarray:
    """One-sided Welch power spectrum of a window's acceleration, the axes summed (the power DFT321 keeps).

    accel: (L,) or (L, k) m/s² with L ≥ segment (columns beyond the first three are ignored: the
    preprocessor's derived columns). Hann segments of `segment` samples, half overlapping, each
    de-meaned; density scaling. Returns (segment // 2 + 1,) (m/s²)²/Hz on `welch_frequencies` — the
    same numbers as scipy.signal.welch (a parity test holds them to it) at a fifth of its per-call cost,
    which matters once per window per session.
    """
    a = np.asarray(accel, float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] < segment or a.shape[1] < 1:
        raise ValueError(f"accel must be (L,) or (L, k) with L ≥ {segment} samples, got shape {np.shape(accel)}")
    if not np.all(np.isfinite(a)):
        raise ValueError("accel holds NaN or Inf")
    index, taper, win_power = _welch_plan(a.shape[0], segment)
    frames = a[:, :3][index]  # (n, segment, axes), a copy: its layout sets the order the mean adds in
    # means as sum / count, which is what ndarray.mean computes, without its Python-level wrapper
    frames -= np.add.reduce(frames, axis=1, keepdims=True) / segment
    frames *= taper
    spectra = np.abs(np.fft.rfft(frames, axis=1))
    spectra **= 2
    psd = (np.add.reduce(spectra, axis=0) / index.shape[0]).sum(axis=1) / (rate_hz * win_power)
    psd[1 : -1 if segment % 2 == 0 else None] *= 2.0  # one-sided: DC (and an even length's Nyquist) once
    return psd


@lru_cache(maxsize=16)
def _welch_plan(length: int, segment: int) -> tuple[np.ndarray, np.ndarray, float]:
    """What window_psd needs for windows of `length` samples, made once per length rather than per window:
    the half-overlapping segments' sample indices (n, segment), the periodic Hann window as scipy.signal.welch
    uses it, shaped (1, segment, 1) to taper (n, segment, axes) frames, and Σ window², its power."""
    hop = segment // 2
    starts = hop * np.arange((length - segment) // hop + 1)
    index = starts[:, None] + np.arange(segment)[None, :]
    win = get_window("hann", segment)
    index.setflags(write=False)
    taper = win[None, :, None]
    taper.setflags(write=False)
    return index, taper, float(np.sum(win**2))


def whittle_mismatch_db(psd: np.ndarray, model_psd: np.ndarray) -> np.ndarray:
    """How unlikely a measured spectrum is under each model, as dB.

    psd: (n,) measured (Welch) spectrum; model_psd: (M, n) model spectra on the same bins.
    Per bin the Whittle negative log-likelihood, less its value at a perfect fit, is r − ln r − 1 with
    r = psd / model (≈ ½ (ln r)² near r = 1); returned as (10 / ln 10)·√(2 · mean over bins), which
    is the RMS log-spectral distance in dB for small differences. Returns (M,) ≥ 0; lower is likelier.
    """
    return _whittle_db(*_checked_pair(psd, model_psd))


def _whittle_db(p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """whittle_mismatch_db without the checks, for spectra known to be finite, ≥ 0 and on the same bins."""
    r = np.maximum(s, _FLOOR)
    np.divide(np.maximum(p, _FLOOR), r, out=r)
    deviance = r - np.log(r)
    deviance -= 1.0
    return _DB * np.sqrt(2.0 * (np.add.reduce(deviance, axis=-1) / r.shape[-1]))


def lsd_mismatch_db(psd: np.ndarray, model_psd: np.ndarray) -> np.ndarray:
    """(M,) RMS difference of 10·log10 spectra, dB: psd (n,) against each row of model_psd (M, n)."""
    return _lsd_db(*_checked_pair(psd, model_psd))


def _lsd_db(p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """lsd_mismatch_db without the checks, for spectra known to be finite, ≥ 0 and on the same bins."""
    d = 10.0 * (np.log10(np.maximum(p, _FLOOR)) - np.log10(np.maximum(s, _FLOOR)))
    return np.sqrt(np.mean(d**2, axis=-1))


def _checked_pair(psd: np.ndarray, model_psd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, s = np.asarray(psd, float), np.asarray(model_psd, float)
    if p.ndim != 1 or s.ndim != 2 or s.shape[1] != p.shape[0] or p.size == 0:
        raise ValueError(f"psd must be (n,) and model_psd (M, n) on the same bins, got {p.shape} and {s.shape}")
    if np.any(p < 0) or np.any(s < 0) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(s))):
        raise ValueError("power spectra must be finite and ≥ 0")
    return p, s


class SpectralTable:
    """Exact ARMA spectra of library models, precomputed on a regular speed–force grid.

    ids: M entry ids; models: their VibrationModels (one rate for all); freqs_hz: (n,) bins to tabulate
    (default: the Welch bins inside the band); the grid spans [0, max speed] × [0, max force] of the
    library with n_speeds × n_forces points. A measured window holds the texture's vibration plus the
    sensor's own noise, so each spectrum is the model's plus noise_psd ((m/s²)²/Hz, flat; default: the
    simulated robot's accelerometer, see `sensor_noise_psd`) — without it a quiet model is "impossible"
    wherever the noise shows. Both pass the service's accelerometer high-pass, applied here too. Stored as
    log10, float32.
    """

    def __init__(
        self,
        ids: Sequence[str],
        models: Sequence[VibrationModel],
        *,
        freqs_hz: np.ndarray | None = None,
        n_speeds: int = 17,
        n_forces: int = 13,
        highpass_hz: float | None = HIGHPASS_HZ,
        highpass_order: int = HIGHPASS_ORDER,
        noise_psd: float | None = None,
    ):
        if len(ids) != len(models) or not ids:
            raise ValueError(f"ids and models must be non-empty and of equal length, got {len(ids)} and {len(models)}")
        if n_speeds < 2 or n_forces < 2:
            raise ValueError(f"the grid needs ≥ 2 speeds and ≥ 2 forces, got {n_speeds} × {n_forces}")
        rates = {float(m.rate_hz) for m in models}
        if len(rates) != 1:
            raise ValueError(f"library models must share one rate, got {sorted(rates)} Hz")
        self.rate_hz = rates.pop()
        if noise_psd is None:
            noise_psd = sensor_noise_psd(SIMULATED_SENSOR_NOISE, rate_hz=self.rate_hz)
        if not (np.isfinite(noise_psd) and noise_psd >= 0):
            raise ValueError(f"noise_psd must be finite and ≥ 0, got {noise_psd}")
        self.noise_psd = float(noise_psd)
        if freqs_hz is None:
            f = welch_frequencies(self.rate_hz)
            freqs_hz = f[band_mask(f)]
        self.ids = list(ids)
        self.freqs_hz = np.asarray(freqs_hz, float)
        self._welch = welch_frequencies(self.rate_hz)
        # the tabulated frequencies are Welch bins (the default): read them, no interpolation
        hits = np.searchsorted(self._welch, self.freqs_hz).clip(0, self._welch.size - 1)
        self._bins = hits if np.allclose(self._welch[hits], self.freqs_hz) else None
        self.speeds = np.linspace(0.0, max(float(m.max_speed) for m in models), n_speeds)
        self.forces = np.linspace(0.0, max(float(m.max_force) for m in models), n_forces)
        # the grids as Python floats: a window's cell is found with bisect, without numpy's per-call overhead
        self._speed_grid = tuple(float(v) for v in self.speeds)
        self._force_grid = tuple(float(v) for v in self.forces)
        ss, ff = np.meshgrid(self.speeds, self.forces, indexing="ij")
        response = np.ones_like(self.freqs_hz)
        if highpass_hz is not None:
            response = 1.0 / (1.0 + (highpass_hz / np.maximum(self.freqs_hz, 1e-9)) ** (2 * highpass_order))
        table = np.empty((len(models), n_speeds, n_forces, self.freqs_hz.size), np.float32)
        for k, m in enumerate(models):
            psd = (arma_psd(m, ss.ravel(), ff.ravel(), self.freqs_hz) + self.noise_psd) * response
            table[k] = np.log10(np.maximum(psd, _FLOOR)).reshape(n_speeds, n_forces, -1)
        table.setflags(write=False)
        self.log_psd = table
        # a finite table gives finite spectra > 0 at every operating point: the per-window path then skips
        # their checks (a non-finite one — a degenerate model — keeps them, and fails as it always did)
        self._finite = bool(np.all(np.isfinite(table)))

    def at(self, speed: float, force: float) -> np.ndarray:
        """(M, n) spectra at one operating point (speed mm/s, force N; clamped to the grid), bilinear in log."""
        if not (np.isfinite(speed) and np.isfinite(force)):
            raise ValueError(f"speed and force must be finite, got {speed}, {force}")
        i, a = _cell(self._speed_grid, speed)
        j, b = _cell(self._force_grid, force)
        a, b = np.float64(a), np.float64(b)  # float64 weights make the mix float64 (a Python float would not)
        t = self.log_psd
        mixed = (
            (1 - a) * (1 - b) * t[:, i, j]
            + a * (1 - b) * t[:, i + 1, j]
            + (1 - a) * b * t[:, i, j + 1]
            + a * b * t[:, i + 1, j + 1]
        )
        # 10^x as e^(x·ln 10): numpy's exp is vectorised, its pow is not (5× the cost here); the two agree to
        # a few ulp, far inside what the float32 table holds
        mixed *= _LN10
        return np.exp(mixed, out=mixed)

    def mismatch_db(self, accel: np.ndarray, speed: float, force: float, kind: str = "whittle") -> np.ndarray:
        """(M,) dB: how far a window's acceleration (L, k) m/s² is from each entry at (speed, force);
        kind "whittle" (likelihood, the `physical` rule) or "lsd" (spectral match, `physical-lsd`)."""
        if kind not in ("whittle", "lsd"):
            raise ValueError(f"kind must be 'whittle' or 'lsd', got {kind!r}")
        full = window_psd(accel, self.rate_hz)
        psd = full[self._bins] if self._bins is not None else np.interp(self.freqs_hz, self._welch, full)
        models = self.at(speed, force)
        if self._finite and np.all(np.isfinite(psd)):
            return _whittle_db(psd, models) if kind == "whittle" else _lsd_db(psd, models)
        return whittle_mismatch_db(psd, models) if kind == "whittle" else lsd_mismatch_db(psd, models)


def _cell(grid: Sequence[float], x: float) -> tuple[int, float]:
    """The grid cell holding x (clamped to the grid) and x's fraction of the way across it: (i, 0 ≤ t ≤ 1)
    with grid[i] ≤ x ≤ grid[i + 1]; grid ascending, ≥ 2 points."""
    x = min(max(float(x), grid[0]), grid[-1])
    i = min(bisect.bisect_right(grid, x) - 1, len(grid) - 2)
    return i, (x - grid[i]) / (grid[i + 1] - grid[i])


@dataclass(frozen=True)
class SelectionRule:
    """A rule's cost per entry from what a window gives: rating distances (M,) (bipolar, the perceptual
    index's) and the physical mismatch (M,) dB (None when the rule does not need it)."""

    name: str = "perceptual"
    weight: float = 0.0  # hybrid: rating units per dB of mismatch

    def __post_init__(self) -> None:
        if self.name not in RULES:
            raise ValueError(f"selection rule must be one of {RULES}, got {self.name!r}")
        if not (np.isfinite(self.weight) and self.weight >= 0):
            raise ValueError(f"the hybrid weight must be finite and ≥ 0, got {self.weight}")

    @property
    def needs_spectrum(self) -> bool:
        return self.name != "perceptual" and not (self.name == "hybrid" and self.weight == 0)

    @property
    def mismatch_kind(self) -> str:
        return "lsd" if self.name == "physical-lsd" else "whittle"

    @property
    def units(self) -> str:
        return {"perceptual": "bipolar", "hybrid": "bipolar + weight·dB"}.get(self.name, "dB")

    def costs(self, rating_distances: np.ndarray | None, mismatch_db: np.ndarray | None) -> np.ndarray:
        if self.name == "perceptual" or (self.name == "hybrid" and self.weight == 0):
            if rating_distances is None:
                raise ValueError(f"rule {self.name!r} needs the rating distances")
            return np.asarray(rating_distances, float)
        if mismatch_db is None:
            raise ValueError(f"rule {self.name!r} needs the window's spectral mismatch")
        if self.name != "hybrid":
            return np.asarray(mismatch_db, float)
        if rating_distances is None:
            raise ValueError("rule 'hybrid' needs the rating distances")
        return np.asarray(rating_distances, float) + self.weight * np.asarray(mismatch_db, float)

    def describe(self, costs: np.ndarray, k: int) -> str:
        """One short sentence: why entry k is the rule's pick by these costs."""
        c = float(costs[k])
        if self.name == "perceptual" or (self.name == "hybrid" and self.weight == 0):
            return f"nearest to the estimated ratings (distance {c:.1f})"
        if self.name == "physical":
            return f"its vibration model best explains the measured vibration (mismatch {c:.1f} dB)"
        if self.name == "physical-lsd":
            return f"its vibration spectrum is nearest to the measured one ({c:.1f} dB)"
        return f"best trade of rating distance and vibration mismatch (cost {c:.1f}, {self.weight:g} per dB)"


@dataclass(frozen=True)
class Choice:
    """What to render after one window: id; rule; reason (one sentence); held_by_hysteresis: the rule's own
    pick this window is another entry; switch_margin: how much cheaper than now, in the rule's units, the best
    other entry must get for the choice to switch at the next window — by the margin, or by its cumulative lead
    (None: the library holds one entry)."""

    id: str
    rule: str
    reason: str
    held_by_hysteresis: bool
    switch_margin: float | None


class HysteresisChooser:
    """Keeps the current choice until a challenger is cheaper by `margin` for `hold` windows in a row, or until
    its cumulative lead — its cost advantage summed over the consecutive windows it is the rule's pick — reaches
    `release_lead` (rule's units; None: no such release).

    The margin alone can stick: a challenger that is steadily cheaper by less than the margin (the smoothed
    estimate of a new surface converging, or a steady stroke that sits between two entries) never takes over.
    The lead releases it after a few windows, while a pick that alternates between near-equal entries restarts
    its lead at every change and so does not flip.

    For its first `settle` windows the chooser follows the rule directly: the smoothed estimate is
    still converging from one window, and holding its first guess would only delay the switch to the
    settled choice (and count as a flip later). `release()` (the scene changed: the tool is over another surface)
    starts such a settling period again, at least one window long, from the next window on."""

    def __init__(
        self,
        rule: SelectionRule,
        margin: float = 5.0,
        hold: int = 2,
        settle: int = 0,
        release_lead: float | None = None,
    ):
        if not (np.isfinite(margin) and margin >= 0) or hold < 1 or settle < 0:
            raise ValueError(f"margin must be finite and ≥ 0, hold ≥ 1 and settle ≥ 0, got {margin}, {hold}, {settle}")
        if release_lead is not None and not (np.isfinite(release_lead) and release_lead > 0):
            raise ValueError(f"release_lead must be finite and > 0 or None, got {release_lead}")
        self.rule, self.margin, self.hold, self.settle = rule, float(margin), int(hold), int(settle)
        self.release_lead = None if release_lead is None else float(release_lead)
        self.current: str | None = None
        self.windows = 0
        self._challenger: str | None = None
        self._streak = 0  # consecutive windows the challenger won by the margin
        self._lead = 0.0  # the challenger's cost advantage summed over the consecutive windows it was the pick
        self._settled_after = self.settle  # windows up to this one follow the rule (release() moves it on)
        self._released = False

    def release(self) -> None:
        """Settle again: the next max(settle, 1) windows follow the rule directly (the scene changed).

        Called from the event loop while a pool thread may be inside `choose`: a flag that `choose` reads and
        clears, so a release racing a window starts with that window or the next."""
        self._released = True

    def choose(self, ids: Sequence[str], costs: np.ndarray) -> Choice:
        c = np.asarray(costs, float)
        if c.shape != (len(ids),) or not ids or not np.all(np.isfinite(c)):
            raise ValueError(f"costs must be {len(ids)} finite values, one per id, got shape {c.shape}")
        k = int(np.argmin(c))
        best = ids[k]
        self.windows += 1
        if self._released:
            self._released = False
            self._settled_after = self.windows - 1 + max(self.settle, 1)
        settling = self.windows <= self._settled_after
        if self.current is None or self.current not in ids or best == self.current or settling:
            # first windows (of the session or a new scene), a library that lost the current entry, or the rule
            # agrees: no hysteresis at work
            self._restart(best)
            why = ""
            if settling:
                why = " — the scene changed" if self.windows > self.settle else ""
                why += " — settling: no hysteresis yet"
            return Choice(best, self.rule.name, self.rule.describe(c, k) + why, False, self._switch_margin(ids, c))
        gain = float(c[list(ids).index(self.current)] - c[k])
        if best != self._challenger:
            self._challenger, self._streak, self._lead = best, 0, 0.0
        self._lead += gain
        self._streak = self._streak + 1 if gain >= self.margin else 0
        if self._streak >= self.hold or (self.release_lead is not None and self._lead >= self.release_lead):
            self._restart(best)
            return Choice(best, self.rule.name, self.rule.describe(c, k), False, self._switch_margin(ids, c))
        return Choice(self.current, self.rule.name, self._keeping(best, gain), True, self._switch_margin(ids, c))

    def _keeping(self, challenger: str, gain: float) -> str:
        """Why the current entry stays, in plain words and the rule's units — the one sentence the terminal and the
        console both show: 'keeping a: b is closer by 2.8; it must be closer by 12 (2 windows in a row), or by
        69.2 more in all, to take over'."""
        need = f"closer by {self.margin:g}"
        if self.hold > 1:
            need += f" ({self.hold} windows in a row" + (f", {self._streak} so far)" if self._streak else ")")
        if self.release_lead is not None:
            need += f", or by {self.release_lead - self._lead:.1f} more in all,"
        return f"keeping {self.current}: {challenger} is closer by {gain:.1f}; it must be {need} to take over"

    def _restart(self, choice: str) -> None:
        self.current, self._challenger, self._streak, self._lead = choice, None, 0, 0.0

    def _switch_margin(self, ids: Sequence[str], c: np.ndarray) -> float | None:
        """How much cheaper than now the best other entry must get to take over at the next window: by the
        margin, or — while it is the challenger — by what its lead still lacks."""
        if len(ids) < 2:
            return None
        cur = list(ids).index(self.current)  # type: ignore[arg-type]
        others = np.delete(c, cur)
        gap = float(c[cur] - others.min())
        needed = self.margin - gap
        if self.release_lead is not None:
            challenger = ids[int(np.argmin(np.where(np.arange(len(ids)) == cur, np.inf, c)))]
            lead = self._lead if challenger == self._challenger else 0.0
            needed = min(needed, self.release_lead - lead - gap)
        return max(0.0, needed)
