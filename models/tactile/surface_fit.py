"""The stroked surface's own rendering model, learnt from the robot's stream as it arrives.

HaTT fits one AR model per recorded (speed, force) operating point (Culbertson et al. 2014); a robot
stroking freely visits a cloud of operating points instead, so here every half-overlapping 128-sample
segment of contact is one noisy look at the spectrum *between* grid points, and the grid points' spectra
are what explains all segments best:

  1. **Normal axis.** The tool's vibration along the surface normal is what a VibrationModel renders. The
     normal is the direction of the accelerometer's mean over contact (gravity, the surface level); the
     segment's acceleration projected onto it, de-meaned, Hann-tapered → a periodogram, (m/s²)²/Hz, on NFFT =
     2·SEGMENT points: zero-padded, its inverse transform is the segment's own autocorrelation, which the AR fit
     reads; on SEGMENT points the lags past SEGMENT/2 wrap onto the short ones (online study, HaTT visited with
     its silent points in: 2.78 / 2.30 dB at 10 / 30 s against 2.86 / 2.61 unpadded).
  2. **Noise floor**, (m/s²)²/Hz on the normal axis: measured from the stream's own contact-free blocks (the
     tool in the air: the band-mean of their periodograms), else the noise density the robot declared,
     else unknown (taken as 0 and said so). Never a constant a simulator uses.
  3. **Bumps.** A bump train z = h(1 + cos 2π(x + x₀)/P)/2 accelerates the tip by z''v² + z'v̇ (texture_library
     .surface): linear in (cos, sin) of the phase at each candidate period P. Least squares over the whole stroke
     (positions are absolute, so the phase is one number per surface) give, per P, the energy the bumps explain. A
     bump profile is a claim that needs evidence: on a bump-free surface the texture's own vibration, coloured and
     louder with speed (as the regressors are), explains energy at every period too — on HaTT strokes 4–7× what
     white noise of the stroke's variance would, so a test against the variance passed 0.05–1 mm "bumps" whose
     period wandered from fit to fit. So each period's explained energy is tested against its **local floor**
     (`bump_floor`: the median over the periods around it, its own line's main lobe left out — a bump-free stroke's
     explained energy is exponential about a mean that varies smoothly with the period), and a profile is reported
     only when the best period (the one that explains most) is BUMP_SIGNIFICANCE times its floor (a chance of ≈
     240·e⁻²⁰ per fit on a bump-free surface) and at least MIN_BUMP_MM high. The evidence of a real bump grows with
     the distance stroked; the floor's does not. Once reported, a period stands (`choose_bump_period`) while it
     keeps BUMP_KEEP_SIGNIFICANCE and the best explains less than BUMP_SWITCH × its floor more, so the profile
     neither flickers in and out nor hops between periods. The fitted bump train (phase and all) is subtracted from
     every segment, and the bins its line swept (v_min/P … v_max/P Hz) are bridged, before the spectral fit.
  4. **Grid spectra, blended with the prior.** Each segment's log periodogram (+ Euler's γ, its bias) is
     modelled as Σₖ wₖ ln(Sₖ(f) + N), wₖ the renderer's barycentric weights of the segment's (speed, force) on
     the grid, N the noise floor; the least-squares ln(Sₖ + N) with a ridge pulling each towards the prior's
     exact spectrum (plus N), as strongly as
     PRIOR_SEGMENTS segments. A grid point with no data is the prior; with many, its own data. A grid
     point's **confidence** is its data's share, Σ w / (Σ w + PRIOR_SEGMENTS).
  5. **ARMA orders and LSFs.** Each grid spectrum (below 20 Hz held at its 20 Hz value: the band the models
     are judged in starts there) → an ARMA fit per candidate (p, q) in ORDERS: poles by Yule–Walker on the
     spectrum over |B|², zeros by Yule–Walker on the inverse spectrum (whose peaks are the notches an AR
     alone smooths over: AR(24) fitted to a HaTT ARMA(20, 18) spectrum stays ≈ 4 dB off), alternated, the
     best iterate kept (the poles alone among them: an ARMA fit is never worse than its AR part). The
     orders, one pair for the whole grid (a VibrationModel's rows share them), minimise **AIC** under the
     Whittle likelihood summed over the grid points, with the samples behind each point (data and prior).
     Each point's likelihood for the choice of orders is taken over the bins it measured, above the noise
     floor: below it a silent prior leaves holes tens of dB deep (HaTT's slowest rows), and one such point's
     likelihood, thousands of nats per sample apart between orders, decided the whole grid's orders and
     flipped them from fit to fit (pink_foam: 36 versions in 60 s, most of them whole). The fit itself reads
     the whole band, so where nothing was measured the prior's values stand (judged on the measured bins
     alone, the model spectra strayed there: 2–3 dB further from the true surface in the online study).
     A caller that holds an earlier fit's pair (`keep_orders`: a session refitting as data accrue) keeps it
     unless the best pair's AIC is lower by ORDER_MARGIN_NATS per sample behind the grid (`choose_orders`):
     near-ties flip from fit to fit, and each flip redraws every grid point's spectrum by ≈ 1–4 dB, so it
     would be a new version that moves the whole grid for no change of the surface.
     The polynomials become LSFs as every stored model keeps them.
  6. **Levels as the renderer plays them.** The renderer blends a model's variances linearly between grid points
     (its LSFs, like log spectra), so a fit true at its grid points rang up to 2.4 dB loud between two points 10 dB
     apart. After the ARMA step the variances are matched to the segments' loudness (`match_levels`: Gauss–Newton
     on each segment's band-mean log level, the shapes kept). Online study, HaTT visited at 2 / 10 s: 2.07 / 1.64 dB
     against 2.83 / 2.05 without; on the synthetic world, where `visited` is ruled by bins below the sensor's
     noise, 10.9 against 9.5 at 10 s, while its `signal` scope holds (the study's report).

Why not Burg on the samples (librosa.lpc)? Burg fits one recording at one operating point and cannot take a
known noise floor out; the averaged periodograms can, at bounded memory (MAX_SEGMENTS segments of 128 samples).
What that costs where Burg is at its best, 10 s at one operating point and no noise (the test module's ARMA(4, 2)
model at 150 mm/s, 2 N): Burg's AR(16) on the samples is 0.34 dB from the truth there, this fit 0.89 dB (1.52
before the levels were matched; the point lies between grid points, which share it with the prior's pull and the
renderer's LSF interpolation).

Friction μ: Σ F_t·F_n / Σ F_n² over contact samples (models.tactile.friction's estimator), blended with the
prior's μ by contact seconds (MU_PRIOR_S). Taps: the last MAX_TAPS accepted tap transients, each the local mean of
its neighbours in speed (models.tactile.taps.local_mean_taps: a recording carries its sensor's noise) (else those of the
first prior the surface was fitted with: the library pick may change from window to window, the surface does
not). Bad input keeps the prior and names one reason (`FitStatus`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from scipy.spatial import Delaunay

from models.tactile.taps import local_mean_taps
from texture_library.lsf import poly_to_lsf
from texture_library.spectrum import BAND_HZ, arma_psd
from texture_library.surface import SurfaceProfile
from texture_library.synthesis import barycentric
from texture_library.taps import TapSet
from texture_library.vibration import RENDER_RATE_HZ, VibrationModel

SEGMENT = 128
HOP = SEGMENT // 2
NFFT = 2 * SEGMENT
#: the fitted model's grid: speeds mm/s × normal forces N (the renderer clamps outside it)
GRID_SPEEDS = (10.0, 40.0, 80.0, 140.0, 220.0, 320.0)
GRID_FORCES = (0.1, 0.6, 1.5, 2.7, 4.2)
#: how many segments of data the library prior counts as, per grid point
PRIOR_SEGMENTS = 2.0
MAX_ORDER = 24
MIN_ORDER = 2
#: at most this many contact segments are kept (the newest): 2048 × 64 samples ≈ 131 s at 1 kHz
MAX_SEGMENTS = 2048
#: contact: normal force at least this (N; force-sensor noise ≈ 0.01 N) and speed at least MIN_SPEED_MM_S
CONTACT_N = 0.05
#: contact-free: normal force below this, N
FREE_N = 0.02
MIN_SPEED_MM_S = 5.0
#: a fit needs this many contact segments (≈ 0.25 s of stroking)
MIN_SEGMENTS = 7
#: a stroke whose band power is within this factor of the noise floor is too noisy to fit
MIN_SNR = 2.0
#: estimated spectra are floored at this fraction of the noise floor (what lies below it is not measured)
NOISE_CLIP = 0.1
#: a period's local floor (bump_floor): the median explained energy over BUMP_FLOOR_HALF periods either side
#: (a factor ≈ 1.65 in period), leaving out BUMP_GUARD either side (± 5 %: the main lobe of a bump's own line once
#: a few hundred mm are stroked)
BUMP_FLOOR_HALF = 40
BUMP_GUARD = 4
#: candidate bump periods, mm: 2–40 mm in 240 geometric steps (BUMP_PERIODS_MM, the ones reported), within a grid
#: that goes on BUMP_FLOOR_HALF + BUMP_GUARD steps either side (BUMP_GRID_MM, 1.2–69 mm), so that every reported
#: period's floor is two-sided: the long periods ring at the lowest frequencies (v/P), where a texture's vibration
#: often rises, and a floor taken from shorter periods alone would pass it as bumps
_BUMP_PAD = BUMP_FLOOR_HALF + BUMP_GUARD
BUMP_GRID_MM = 2.0 * (40.0 / 2.0) ** (np.arange(-_BUMP_PAD, 240 + _BUMP_PAD) / 239.0)
BUMP_PERIODS_MM = BUMP_GRID_MM[_BUMP_PAD:-_BUMP_PAD]
#: a bump profile is reported when its period's explained energy is this many times its local floor's mean (under
#: no bumps the ratio is exponential with mean 1: a chance of ≈ 240 periods × e⁻²⁰ ≈ 5e-7 per fit); a bump-free
#: HaTT stroke reaches 4–7 at its best period, the test module's 0.6 mm bumps ≈ 100 after 5 s
BUMP_SIGNIFICANCE = 20.0
#: a reported period stands while it keeps this significance (hysteresis: a profile does not flicker in and out)
BUMP_KEEP_SIGNIFICANCE = 10.0
#: … and until the best period explains this many of its floor's means more (evidence: a chance of ≈ e⁻¹⁰ under no
#: bumps; a real bump's true period soon outgrows an early, slightly wrong one by far more)
BUMP_SWITCH = 10.0
#: a bump decision needs this much contact path, mm
MIN_BUMP_PATH_MM = 100.0
#: bumps lower than this are no bumps, mm: the texture's own (coloured) vibration leaks into the regression a
#: little at every period, so significance alone passes micrometre "bumps" on a flat surface
MIN_BUMP_MM = 0.02
MU_PRIOR_S = 0.25
#: the fitted variances are matched to the segments' loudness (match_levels) until no grid point moves
#: LEVEL_TOLERANCE nepers (≈ 0.02 dB), at most LEVEL_ITERATIONS times
LEVEL_ITERATIONS = 20
LEVEL_TOLERANCE = 0.005
#: the least spectral density a fit holds, (m/s²)²/Hz: ≈ 60 dB below an accelerometer's noise floor
SPECTRUM_FLOOR = 1e-12
MAX_TAPS = 16
#: a block clips when an axis sits at its extreme for at least this many consecutive samples
CLIP_RUN = 3
#: the AR fit's lag window (Gaussian, in Hz of bandwidth) and white-noise correction: keep the roots inside
LAG_WINDOW_HZ = 2.0
WHITE_NOISE_CORRECTION = 1e-6


class FitStatus(StrEnum):
    """Why the model still is (or went back to) the prior; `ok` when the data are used."""

    ok = "ok"
    no_contact = "no contact yet: the camera's pick stands"
    too_short = "stroke too short to fit"
    too_slow = "stroke too slow to fit"
    too_noisy = "stroke too noisy to fit: its vibration is within 3 dB of the sensor's noise floor"
    clipping = "accelerometer clipping: the block was left out"
    constant = "constant or all-zero accelerometer signal: the block was left out"
    scene_change = "the surface changed mid-fit: restarted from the prior"


@dataclass(frozen=True)
class SurfaceFit:
    """A snapshot of what the stream says about the surface.

    model: the blended VibrationModel (the prior itself before any usable contact); status: why it is not
    (yet) the data's; confidence: (m,) per grid point of model, the data's share in [0, 1] (zeros when the
    model is the prior); order: the AR order chosen by AIC (0: the prior's; the MA order:
    extra['orders']); noise_psd: the noise floor
    used, (m/s²)²/Hz; noise_source: "contact-free blocks", "declared" or "unknown"; contact_s: seconds of
    contact used.
    """

    model: VibrationModel
    status: FitStatus
    confidence: np.ndarray
    order: int
    noise_psd: float
    noise_source: str
    contact_s: float
    bumps: SurfaceProfile | None = None
    extra: dict = field(default_factory=dict)


# ---- pure pieces -----------------------------------------------------------------------------------------
def levinson(r: np.ndarray, max_order: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Levinson–Durbin on autocorrelation r (≥ max_order + 1,): the monic AR polynomials of orders
    1 … max_order and their prediction-error variances (max_order,)."""
    r = np.asarray(r, float)
    if r.ndim != 1 or r.size < max_order + 1 or max_order < 1:
        raise ValueError(f"r must be 1-D with at least max_order + 1 = {max_order + 1} lags, got {r.shape}")
    if not r[0] > 0:
        raise ValueError(f"r[0] (the variance) must be > 0, got {r[0]}")
    a = np.array([1.0])
    err = float(r[0])
    polys, errs = [], np.empty(max_order)
    for p in range(1, max_order + 1):
        k = -float(np.dot(a, r[p:0:-1])) / err
        a = np.concatenate([a, [0.0]]) + k * np.concatenate([a, [0.0]])[::-1]
        err *= 1.0 - k * k
        err = max(err, 1e-300)
        polys.append(a.copy())
        errs[p - 1] = err
    return polys, errs


def autocorrelation_from_psd(psd: np.ndarray, rate_hz: float) -> np.ndarray:
    """psd: (n//2 + 1,) one-sided density on rfft bins of an n-point segment, (m/s²)²/Hz → (n,) autocorrelation
    r[l], (m/s²)², with r[0] the variance (∫ psd df)."""
    s = np.asarray(psd, float).copy()
    s[1:-1] *= 0.5  # one-sided → two-sided, DC and Nyquist once
    return np.fft.irfft(s * rate_hz)


def ar_from_psd(
    psd: np.ndarray, rate_hz: float, n_eff: float, max_order: int = MAX_ORDER
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Candidate AR fits of a spectrum: (polynomials of orders 1…max_order, their innovation variances,
    AIC per order = n_eff·ln σ²(p) + 2p). psd: (SEGMENT//2 + 1,) (m/s²)²/Hz; n_eff: samples behind it."""
    r = autocorrelation_from_psd(psd, rate_hz)
    lags = np.arange(r.size)
    r = r * np.exp(-0.5 * (2 * np.pi * LAG_WINDOW_HZ * lags / rate_hz) ** 2)
    r[0] *= 1.0 + WHITE_NOISE_CORRECTION
    polys, errs = levinson(r, max_order)
    aic = n_eff * np.log(errs) + 2.0 * np.arange(1, max_order + 1)
    return polys, errs, aic


#: the (AR, MA) orders an ARMA fit chooses among (HaTT's models are ARMA of about (20, 18))
ORDERS: tuple[tuple[int, int], ...] = tuple(
    (p, q) for p in (4, 8, 12, 16, 20, 24) for q in sorted({0, p // 2, max(p - 2, 0)})
)
ARMA_ITERATIONS = 3
#: a grid point's orders are judged on its measured bins when it has at least this many (else on the whole band)
MIN_JUDGED_BINS = 8
#: an earlier fit's (AR, MA) orders stand unless the best pair lowers the AIC by this much per sample behind the
#: grid (nats: the mean Whittle log-likelihood per sample; 0.02 ≈ 0.09 dB of innovation variance). Measured on
#: HaTT strokes (python -m benchmarks.publish_policy): it removes most order flips for +0.03 dB from the truth,
#: where 0.1 cost 0.24 dB
ORDER_MARGIN_NATS = 0.02


def _poly_power(poly: np.ndarray, n_fft: int) -> np.ndarray:
    """|P(e^{jω})|² on the n_fft//2 + 1 rfft bins."""
    return np.abs(np.fft.rfft(poly, n_fft)) ** 2


def arma_from_psd(
    psd: np.ndarray,
    rate_hz: float,
    n_eff: float,
    band: np.ndarray,
    orders: tuple[tuple[int, int], ...] = ORDERS,
    judged: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """ARMA fits of a spectrum, one per (p, q) in `orders`: (a (p+1,), b (q+1,), variance, AIC).

    psd: (n//2 + 1,) one-sided density on rfft bins, (m/s²)²/Hz; band: (n//2 + 1,) bool, the bins judged; n_eff:
    samples behind the spectrum. Poles from Yule–Walker on S/|B|², zeros from Yule–Walker on the inverse spectrum
    1/(S|A|²) (whose peaks are S's notches), alternated ARMA_ITERATIONS times, the iterate (B = 1, the poles alone,
    included) with the best Whittle likelihood kept; the variance matches the model to S in mean log power over the
    band (the log-spectral optimum). AIC under the Whittle likelihood: n_band·mean_band(ln Ŝ + S/Ŝ) + 2(p + q + 1),
    n_band = n_eff · (band share) the independent bins behind the band. judged: (n//2 + 1,) bool within band, the
    bins measured (above the noise floor: `SurfaceFitter.fit`), where the AIC's likelihood is taken (None, or fewer
    than MIN_JUDGED_BINS: the band) — a hole below the noise floor (the prior's, tens of dB deep) would otherwise
    decide the orders; the fit (poles, zeros, level) reads the whole band either way."""
    s = np.maximum(np.asarray(psd, float), 1e-300)
    n_fft = 2 * (s.size - 1)
    orders_band = band
    if judged is not None and int(np.count_nonzero(judged & band)) >= MIN_JUDGED_BINS:
        orders_band = judged & band
    n_band = n_eff * orders_band.mean()

    def whittle(a: np.ndarray, b: np.ndarray, on: np.ndarray = band) -> tuple[float, float]:
        # (the Whittle term per band bin, the variance) of the pair, variance at the log-spectral optimum
        shape = 2.0 * _poly_power(b, n_fft) / (rate_hz * _poly_power(a, n_fft))
        variance = float(np.exp(np.mean(np.log(s[on] / shape[on]))))
        model = variance * shape
        return float(np.mean(np.log(model[on]) + s[on] / model[on])), variance

    out = []
    for p, q in orders:
        b = np.concatenate([[1.0], np.zeros(q)])
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        # Levinson's polynomials are minimum-phase: only the final pair needs its LSFs checked (root finding is
        # most of a fit's cost). The alternation is not monotone: on a spectrum with a deep hole (tens of dB below
        # the noise floor, where the prior stands) the zeros fitted to the inverse spectrum can put notches where
        # there are none and leave the pair thousands of nats per sample worse than its own poles alone (b = 1),
        # which then decided the whole grid's orders and flipped them from fit to fit. So every iterate is scored
        # and the best kept, the first being the poles alone: an ARMA(p, q) fit is never worse than AR(p).
        for _ in range(ARMA_ITERATIONS if q else 1):
            polys, _, _ = ar_from_psd(s / _poly_power(b, n_fft), rate_hz, 1.0, max_order=p)
            a = polys[p - 1]
            score = whittle(a, b)[0]
            if best is None or score < best[0]:
                best = (score, a, b)
            if not q:
                break
            inverse = 1.0 / (s * _poly_power(a, n_fft))
            inverse /= inverse[band].mean()
            polys, _, _ = ar_from_psd(inverse, rate_hz, 1.0, max_order=q)
            b = polys[q - 1]
            score = whittle(a, b)[0]
            if score < best[0]:
                best = (score, a, b)
        assert best is not None
        a = _pull_in(best[1])
        b = _pull_in(best[2]) if q else best[2]
        variance = whittle(a, b)[1]
        score = whittle(a, b, orders_band)[0]
        out.append((a, b, variance, n_band * score + 2.0 * (p + q + 1)))
    return out


def choose_orders(aic: np.ndarray, n_samples: float, keep: int | None = None) -> int:
    """The index of the (AR, MA) pair to use: the lowest AIC, or `keep` (an earlier fit's pair) while the best
    beats it by less than ORDER_MARGIN_NATS × n_samples. aic: (len(ORDERS),) summed over the grid; n_samples:
    the samples behind the grid (data and prior), > 0."""
    aic = np.asarray(aic, float)
    if aic.ndim != 1 or aic.size == 0 or not np.all(np.isfinite(aic)):
        raise ValueError(f"aic must be a non-empty 1-D array of finite numbers, got shape {aic.shape}")
    if not n_samples > 0:
        raise ValueError(f"n_samples must be > 0, got {n_samples}")
    best = int(np.argmin(aic))
    if keep is None:
        return best
    if not 0 <= keep < aic.size:
        raise ValueError(f"keep must index one of the {aic.size} order pairs, got {keep}")
    return keep if aic[keep] - aic[best] < ORDER_MARGIN_NATS * n_samples else best


def _pull_in(poly: np.ndarray) -> np.ndarray:
    """The polynomial with its roots pulled inside the unit circle until its LSFs resolve (bandwidth expansion)."""
    a = np.asarray(poly, float)
    for gamma in (1.0, 0.999, 0.995, 0.99, 0.98, 0.95, 0.9):
        c = a * gamma ** np.arange(a.size)
        try:
            poly_to_lsf(c)
            return c
        except ValueError:
            continue
    raise ValueError("polynomial too close to instability for LSFs even after bandwidth expansion")


def clipped(accel: np.ndarray, run: int = CLIP_RUN) -> bool:
    """True when any axis of accel (n, k) sits at its own extreme value for `run` consecutive samples — a
    saturated accelerometer; real vibration never repeats its peak exactly."""
    a = np.asarray(accel, float)
    if a.ndim == 1:
        a = a[:, None]
    if a.shape[0] < run:
        return False
    for col in a.T:
        for extreme in (col.max(), col.min()):
            at = np.abs(col - extreme) <= 1e-9 * max(1.0, abs(extreme))
            if at.sum() >= run:
                # longest run of consecutive samples at the extreme
                edges = np.diff(np.concatenate([[0], at.astype(np.int8), [0]]))
                if (np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)).max() >= run:
                    return True
    return False


def constant(accel: np.ndarray) -> bool:
    """True when every axis of accel (n, k) is constant (all-zero included)."""
    a = np.asarray(accel, float)
    return bool(a.size == 0 or np.all(np.ptp(a, axis=0) <= 1e-9))


def bump_regressors(x: np.ndarray, v: np.ndarray, dv: np.ndarray, periods_mm: np.ndarray) -> np.ndarray:
    """(len(periods), n, 2): per candidate period P, the tip acceleration (m/s²) of the bump trains
    (h/2)·(cos, sin) phase = (1, 0) and (0, 1): −1e-3·[k²v² cos kx + k v̇ sin kx, −k²v² sin kx + k v̇ cos kx],
    k = 2π/P. x: (n,) mm; v: (n,) signed mm/s; dv: (n,) mm/s²."""
    k = (2 * np.pi / np.asarray(periods_mm, float))[:, None]
    c, s = np.cos(k * x[None, :]), np.sin(k * x[None, :])
    kv2, kdv = k * k * (v * v)[None, :], k * dv[None, :]
    return -1e-3 * np.stack([kv2 * c + kdv * s, -kv2 * s + kdv * c], axis=-1)


def bump_floor(explained: np.ndarray, half: int = BUMP_FLOOR_HALF, guard: int = BUMP_GUARD) -> np.ndarray:
    """(P,) the energy each candidate bump period would explain on a bump-free surface (its mean), same unit.

    explained: (P,) energy the least-squares bump train of each period explains, on periods in geometric order;
    half, guard: periods (indices). Without bumps, a period's explained energy is exponential (two regressors'
    worth of the texture's coloured, speed-dependent vibration) about a mean that varies smoothly with the period;
    that mean is the median of the 2·half periods around it, its own guard either side left out (the window slides
    inwards at the ends), over ln 2 (an exponential's median). explained / floor is then ≈ exponential with mean 1
    under no bumps; a real bump train's grows with the distance stroked."""
    e = np.asarray(explained, float)
    if e.ndim != 1 or e.size < 2 * (half + guard) + 1 or not np.all(np.isfinite(e)) or np.any(e < 0):
        raise ValueError(
            f"explained must be 1-D, finite, ≥ 0 and longer than 2·(half + guard) = {2 * (half + guard)}, "
            f"got shape {e.shape}"
        )
    if half < 1 or guard < 0:
        raise ValueError(f"half must be ≥ 1 and guard ≥ 0, got {half} and {guard}")
    n, width = e.size, 2 * (half + guard) + 1
    out = np.empty(n)
    for i in range(n):
        lo = min(max(i - half - guard, 0), n - width)
        window = np.concatenate([e[lo : max(i - guard, lo)], e[min(i + guard + 1, lo + width) : lo + width]])
        out[i] = float(np.median(window)) / math.log(2.0)
    return out


def choose_bump_period(explained: np.ndarray, floor: np.ndarray, kept: int | None = None) -> int | None:
    """The index of the bump period to report, or None (no bumps).

    explained: (P,) the energy each period's bump train explains; floor: (P,) its mean under no bumps (bump_floor);
    kept: the period reported by the previous decision (None: none). The period is the one that explains most (the
    least-squares estimate). The kept period stands while its significance (explained / floor) is at least
    BUMP_KEEP_SIGNIFICANCE and the best explains less than BUMP_SWITCH of its floor more; otherwise the best, when
    its significance reaches BUMP_SIGNIFICANCE."""
    e = np.asarray(explained, float)
    fl = np.asarray(floor, float)
    if e.ndim != 1 or e.shape != fl.shape or e.size == 0 or np.isnan(e).any() or np.isnan(fl).any():
        raise ValueError(
            f"explained and floor must be 1-D of one non-zero length without NaN, got {e.shape}, {fl.shape}"
        )
    if kept is not None and not 0 <= kept < e.size:
        raise ValueError(f"kept must index one of the {e.size} periods, got {kept}")
    z = np.divide(e, fl, out=np.where(e > 0, math.inf, 0.0), where=fl > 0)
    best = int(np.argmax(e))
    if kept is not None and z[kept] >= BUMP_KEEP_SIGNIFICANCE and e[best] - e[kept] < BUMP_SWITCH * fl[kept]:
        return kept
    return best if z[best] >= BUMP_SIGNIFICANCE else None


def match_levels(
    variance: np.ndarray,
    weights: np.ndarray,
    unit: np.ndarray,
    data_level: np.ndarray,
    noise_psd: float,
    prior_segments: float,
) -> np.ndarray:
    """(m,) grid-point variances, (m/s²)², under which what the renderer plays at each segment is as loud as the
    segment was.

    The spectra are fitted in log power (as LSFs blend), but the renderer blends variances linearly
    (texture_library.synthesis.interpolate): between two grid points 10 dB apart the linear blend is up to 2.4 dB
    louder than the log one, so a fit true at its grid points rang loud between them. The log variances take
    Gauss–Newton steps on the segments' log-level residuals (least squares over the segments, each step damped by
    prior_segments: a grid point no segment touches keeps its variance) until no point moves LEVEL_TOLERANCE nepers
    (at most LEVEL_ITERATIONS times). variance: (m,) the fit's; weights: (k, m) the segments' barycentric weights;
    unit: (k, n) each segment's unit-variance model spectrum at its (speed, force) over the band, 1/Hz; data_level:
    (k,) each segment's band mean of ln P + γ (P its periodogram, (m/s²)²/Hz); noise_psd: the floor, (m/s²)²/Hz."""
    w, u, level = np.asarray(weights, float), np.asarray(unit, float), np.asarray(data_level, float)
    v = np.asarray(variance, float)
    k, m = w.shape if w.ndim == 2 else (-1, -1)
    if v.shape != (m,) or u.ndim != 2 or u.shape[0] != k or level.shape != (k,):
        raise ValueError(
            f"need variance (m,), weights (k, m), unit (k, n) and data_level (k,), got {v.shape}, {w.shape}, "
            f"{u.shape}, {level.shape}"
        )
    log_var = np.log(np.maximum(v, SPECTRUM_FLOOR))
    for _ in range(LEVEL_ITERATIONS):
        var = np.exp(log_var)
        played = np.maximum((w @ var)[:, None] * u + noise_psd, SPECTRUM_FLOOR)
        residual = level - np.log(played).mean(axis=1)
        # Gauss–Newton in the log variances: ∂ mean ln played_s / ∂ ln v_j = mean_f w_sj v_j u_sf / played_sf
        jac = w * var[None, :] * (u / played).mean(axis=1)[:, None]
        step = np.linalg.solve(jac.T @ jac + prior_segments * np.eye(m), jac.T @ residual)
        log_var += step
        if np.max(np.abs(step)) < LEVEL_TOLERANCE:
            break
    return np.exp(log_var)


# ---- the streaming fitter --------------------------------------------------------------------------------
class SurfaceFitter:
    """Accumulates a session's accepted blocks into bounded statistics; `fit(prior)` makes the model.

    Memory: at most max_segments (default MAX_SEGMENTS) segments (normal acceleration, velocity and position,
    128 float32 each: 3 MB at the default; kept raw so that bumps found later come off every segment before its
    spectrum is taken), the bump normal equations (328 periods × 5 numbers), MAX_TAPS taps, a few running sums;
    CPU per block: one FFT per 64 samples and 328 × n trigonometric terms. `fit` costs a (30 × 30) solve, the ARMA
    fits of 30 grid points (Levinson recursions) and at most LEVEL_ITERATIONS (30 × 30) Gauss–Newton solves: ≈ 0.35 s
    of one core at 2,048 segments (python -m benchmarks.surface_model, AMD EPYC).
    """

    def __init__(
        self, rate_hz: float = RENDER_RATE_HZ, declared_noise_psd: float | None = None, max_segments: int = MAX_SEGMENTS
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        if max_segments < MIN_SEGMENTS:
            raise ValueError(f"max_segments must be ≥ {MIN_SEGMENTS} (a fit's minimum), got {max_segments}")
        self.max_segments = int(max_segments)
        if declared_noise_psd is not None and not (math.isfinite(declared_noise_psd) and declared_noise_psd >= 0):
            raise ValueError(f"declared_noise_psd must be finite and ≥ 0 (m/s²)²/Hz, got {declared_noise_psd}")
        self.rate_hz = float(rate_hz)
        self.declared_noise_psd = declared_noise_psd
        speeds, forces = np.meshgrid(GRID_SPEEDS, GRID_FORCES, indexing="ij")
        self.grid_speeds, self.grid_forces = speeds.ravel(), forces.ravel()
        norm = np.stack([self.grid_speeds / max(GRID_SPEEDS), self.grid_forces / max(GRID_FORCES)], axis=1)
        self.triangles = Delaunay(norm).simplices.astype(np.int64)
        m = self.grid_speeds.size
        self._template = VibrationModel(
            name="grid",
            speeds=self.grid_speeds,
            forces=self.grid_forces,
            triangles=self.triangles,
            ar_lsf=np.tile([1.0, 2.0], (m, 1)),
            ma_lsf=np.zeros((m, 0)),
            variance=np.ones(m),
            gain=np.ones(m),
            mu=0.0,
            max_speed=max(GRID_SPEEDS),
            max_force=max(GRID_FORCES),
        )
        self.freqs = np.fft.rfftfreq(NFFT, 1.0 / self.rate_hz)
        self._taper = np.hanning(SEGMENT + 1)[:-1]  # periodic Hann
        self._win_power = float(np.sum(self._taper**2))
        self.reset()

    def reset(self) -> None:
        """Forget the surface (a scene change): back to the prior."""
        m = self.grid_speeds.size
        self._pending = np.zeros((0, 6))  # accel x3, normal force, signed speed, position
        self._gravity = np.zeros(3)
        self._gravity_n = 0
        k = self.max_segments
        self._raw = np.zeros((k, 3, SEGMENT), np.float32)  # normal accel, signed velocity, position
        self._idx = np.zeros((k, 3), np.int64)
        self._w = np.zeros((k, 3))
        self._vrange = np.zeros((k, 2))
        self._op = np.zeros((k, 2))  # each segment's mean speed (mm/s) and normal force (N)
        self._count = 0  # segments seen (the ring's write position is count % max_segments)
        self._slow = 0
        self._free_sum, self._free_n = 0.0, 0
        self._free_pending = np.zeros((0, 3))
        nper = BUMP_GRID_MM.size
        self._bump_g = np.zeros((nper, 2, 2))
        self._bump_b = np.zeros((nper, 2))
        self._bump_ss = 0.0
        self._bump_n = 0
        self._bump_kept: int | None = None  # the period last reported (choose_bump_period's hysteresis)
        self._path_mm = 0.0
        self._mu_num = self._mu_den = 0.0
        self._contact_samples = 0
        self._taps: list[tuple[float, np.ndarray]] = []
        self._fallback_taps: tuple[TapSet | None] | None = None  # (the first prior's taps,) once a fit used one
        self._last_reason: FitStatus | None = None
        del m

    def scene_change(self) -> FitStatus:
        """The robot moved to another surface: everything learnt so far is dropped."""
        self.reset()
        self._last_reason = FitStatus.scene_change
        return FitStatus.scene_change

    # ---- input -----------------------------------------------------------------------------------------
    def push(
        self,
        accel: np.ndarray,
        force: np.ndarray,
        speed: np.ndarray,
        position: np.ndarray | None = None,
    ) -> FitStatus | None:
        """One accepted block at rate_hz: accel (n, 3) m/s²; force (n, 3) N (tangential x, y, normal) or (n,)
        normal only; speed (n,) mm/s; position (n,) signed mm along the stroke (None: the integral of speed,
        which keeps bump periods but not their phase across reversals). Returns a reason when the block was
        left out (clipping, constant signal), else None."""
        a = np.asarray(accel, float)
        f = np.asarray(force, float)
        v = np.asarray(speed, float)
        n = a.shape[0] if a.ndim == 2 else -1
        if a.ndim != 2 or a.shape[1] != 3 or f.shape[0] != n or v.shape != (n,):
            raise ValueError(
                f"need accel (n, 3), force (n,) or (n, 3) and speed (n,), got {a.shape}, {f.shape}, {v.shape}"
            )
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(f)) and np.all(np.isfinite(v))):
            raise ValueError("accel, force and speed must be finite")
        if n == 0:
            return None
        if constant(a):
            self._last_reason = FitStatus.constant
            return FitStatus.constant
        if clipped(a):
            self._last_reason = FitStatus.clipping
            return FitStatus.clipping
        if f.ndim == 2:
            if f.shape[1] != 3:
                raise ValueError(f"force must be (n,) or (n, 3), got {f.shape}")
            normal, tangential = f[:, 2], np.hypot(f[:, 0], f[:, 1])
        else:
            normal, tangential = f, None
        if position is None:
            x = self._path_mm + np.cumsum(np.abs(v)) / self.rate_hz
        else:
            x = np.asarray(position, float)
            if x.shape != (n,) or not np.all(np.isfinite(x)):
                raise ValueError(f"position must be finite (n,) = ({n},), got {x.shape}")
        touching = normal >= CONTACT_N
        free = normal < FREE_N
        if free.any():
            self._free_pending = np.concatenate([self._free_pending, a[free]])[-4 * SEGMENT :]
            self._take_free()
        if touching.any():
            self._gravity += a[touching].sum(axis=0)
            self._gravity_n += int(touching.sum())
            self._contact_samples += int(touching.sum())
            if tangential is not None:
                self._mu_num += float(np.dot(tangential[touching], normal[touching]))
                self._mu_den += float(np.dot(normal[touching], normal[touching]))
        # signed velocity from position (its sign says the direction), magnitude from the speed channel
        direction = np.sign(np.diff(x, prepend=x[0] - (x[1] - x[0] if n > 1 else 0.0)))
        direction[direction == 0] = 1.0
        rows = np.column_stack([a, np.where(touching, normal, np.nan), direction * np.abs(v), x])
        self._pending = np.concatenate([self._pending, rows])
        self._path_mm += float(np.abs(v[touching]).sum() / self.rate_hz)
        self._take_segments()
        return None

    def push_taps(self, speeds: np.ndarray, accel: np.ndarray) -> FitStatus | None:
        """Tap transients: speeds (k,) mm/s; accel (k, n) m/s² at rate_hz. Clipped or flat taps are left out."""
        s = np.asarray(speeds, float)
        a = np.asarray(accel, float)
        if s.ndim != 1 or a.ndim != 2 or a.shape[0] != s.size:
            raise ValueError(f"taps need speeds (k,) and accel (k, n), got {s.shape} and {a.shape}")
        reason = None
        for speed, trace in zip(s, a):
            if constant(trace[:, None]):
                reason = FitStatus.constant
            elif clipped(trace[:, None]):
                reason = FitStatus.clipping
            elif np.isfinite(speed) and speed > 0 and np.all(np.isfinite(trace)):
                self._taps.append((float(speed), trace.copy()))
        self._taps = self._taps[-MAX_TAPS:]
        if reason is not None:
            self._last_reason = reason
        return reason

    def _take_free(self) -> None:
        while self._free_pending.shape[0] >= SEGMENT:
            seg = self._free_pending[:SEGMENT]
            self._free_pending = self._free_pending[HOP:]
            axis = self._normal_axis()
            p = self._periodogram(seg @ axis)
            band = (self.freqs >= BAND_HZ[0]) & (self.freqs < BAND_HZ[1])
            self._free_sum += float(p[band].mean())
            self._free_n += 1

    def _normal_axis(self) -> np.ndarray:
        g = self._gravity if self._gravity_n else self._free_gravity()
        norm = float(np.linalg.norm(g))
        return g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])

    def _free_gravity(self) -> np.ndarray:
        return self._free_pending.mean(axis=0) if self._free_pending.size else np.zeros(3)

    def _periodogram(self, x: np.ndarray) -> np.ndarray:
        y = (x - x.mean()) * self._taper
        p = np.abs(np.fft.rfft(y, NFFT)) ** 2 / (self.rate_hz * self._win_power)
        p[1:-1] *= 2.0
        return p

    def _take_segments(self) -> None:
        rows = self._pending
        while rows.shape[0] >= SEGMENT:
            seg = rows[:SEGMENT]
            rows = rows[HOP:]
            normal = seg[:, 3]
            if np.isnan(normal).any():  # not in contact throughout
                continue
            speed = np.abs(seg[:, 4])
            if speed.mean() < MIN_SPEED_MM_S:
                self._slow += 1
                continue
            axis = self._normal_axis()
            an = seg[:, :3] @ axis
            self._accumulate_bumps(an, seg[:, 4], seg[:, 5])
            slot = self._count % self.max_segments
            self._raw[slot] = an, seg[:, 4], seg[:, 5]
            idx, w = barycentric(self._template, np.array([speed.mean()]), np.array([normal.mean()]))
            self._idx[slot], self._w[slot] = idx[0], w[0]
            self._vrange[slot] = speed.min(), speed.max()
            self._op[slot] = speed.mean(), normal.mean()
            self._count += 1
        self._pending = rows

    def _accumulate_bumps(self, an: np.ndarray, v: np.ndarray, x: np.ndarray) -> None:
        # only the hop's new samples, so overlapping segments count each sample once; gravity (the running
        # mean along the normal) comes off, not the hop's own mean, which would take slow bumps with it
        dv = (np.gradient(v) * self.rate_hz)[-HOP:]
        an, v, x = an[-HOP:], v[-HOP:], x[-HOP:]
        y = an - float(np.linalg.norm(self._gravity)) / max(self._gravity_n, 1)
        r = bump_regressors(x, v, dv, BUMP_GRID_MM)  # (P, n, 2)
        self._bump_g += np.einsum("pni,pnj->pij", r, r)
        self._bump_b += np.einsum("pni,n->pi", r, y)
        self._bump_ss += float(y @ y)
        self._bump_n += y.size

    def grid_model(
        self,
        spectra: np.ndarray,
        n_eff: np.ndarray,
        judged: np.ndarray | None = None,
        name: str = "surface",
        mu: float = 0.0,
        keep_orders: tuple[int, int] | None = None,
    ) -> tuple[VibrationModel, tuple[int, int]]:
        """The VibrationModel on the fitter's grid that renders `spectra`, and its (AR, MA) orders: one ARMA fit per
        grid point (arma_from_psd), one order pair for all chosen by the AIC summed over the grid (choose_orders,
        keeping `keep_orders` unless clearly beaten), each row's polynomials as LSFs.

        spectra: (m, NFFT//2 + 1) (m/s²)²/Hz on self.freqs, one row per grid point; n_eff: (m,) samples behind each;
        judged: (m, NFFT//2 + 1) bool, the bins a row's orders are judged on (None: the band); mu: the friction
        coefficient the model carries."""
        m = self.grid_speeds.size
        spectra = np.asarray(spectra, float)
        if spectra.shape != (m, self.freqs.size) or np.asarray(n_eff).shape != (m,):
            raise ValueError(
                f"spectra must be (m, bins) = ({m}, {self.freqs.size}) and n_eff ({m},), got {spectra.shape} and "
                f"{np.asarray(n_eff).shape}"
            )
        band = (self.freqs >= BAND_HZ[0]) & (self.freqs < BAND_HZ[1])
        rows = judged if judged is not None else np.broadcast_to(band, spectra.shape)
        fits = [arma_from_psd(sp, self.rate_hz, float(n), band, judged=jb) for sp, n, jb in zip(spectra, n_eff, rows)]
        aic = np.sum([[f[3] for f in per] for per in fits], axis=0)
        keep = ORDERS.index(keep_orders) if keep_orders in ORDERS else None
        best = choose_orders(aic, float(np.sum(n_eff)), keep)
        p, q = ORDERS[best]
        ar_lsf, ma_lsf, variance = np.empty((m, p)), np.empty((m, q)), np.empty(m)
        for j, per in enumerate(fits):
            a, b, var, _ = per[best]
            ar_lsf[j], ma_lsf[j], variance[j] = poly_to_lsf(a), poly_to_lsf(b), var
        model = VibrationModel(
            name=name,
            speeds=self.grid_speeds.copy(),
            forces=self.grid_forces.copy(),
            triangles=self.triangles.copy(),
            ar_lsf=ar_lsf,
            ma_lsf=ma_lsf,
            variance=variance,
            gain=np.ones(m),
            mu=mu,
            max_speed=max(GRID_SPEEDS),
            max_force=max(GRID_FORCES),
            rate_hz=self.rate_hz,
        )
        return model, (p, q)

    def _match_levels(
        self,
        model: VibrationModel,
        weights: np.ndarray,
        data_level: np.ndarray,
        noise_psd: float,
        prior_segments: float,
    ) -> VibrationModel:
        """The model with its variances matched to the segments' loudness (`match_levels`), each segment's
        unit-variance spectrum taken at its own (speed, force) over the band."""
        freqs = self.freqs[(self.freqs >= BAND_HZ[0]) & (self.freqs < BAND_HZ[1])]
        op = self._op[: data_level.size]
        unit = arma_psd(replace(model, variance=np.ones_like(model.variance)), op[:, 0], op[:, 1], freqs)
        variance = match_levels(model.variance, weights, unit, data_level, noise_psd, prior_segments)
        return replace(model, variance=variance)

    # ---- estimates -------------------------------------------------------------------------------------
    @property
    def holds_fallback_taps(self) -> bool:
        """Whether a fit since the last reset fixed the surface's fallback taps (its first prior's)."""
        return self._fallback_taps is not None

    @property
    def segments(self) -> int:
        return min(self._count, self.max_segments)

    def noise(self) -> tuple[float, str]:
        """The noise floor on the normal axis, (m/s²)²/Hz, and where it came from."""
        if self._free_n >= 4:
            return self._free_sum / self._free_n, "contact-free blocks"
        if self.declared_noise_psd is not None:
            return float(self.declared_noise_psd), "declared"
        return 0.0, "unknown"

    def mu(self, prior_mu: float) -> float:
        if self._mu_den <= 0:
            return prior_mu
        t = self._contact_samples / self.rate_hz
        w = t / (t + MU_PRIOR_S)
        return float(w * (self._mu_num / self._mu_den) + (1 - w) * prior_mu)

    def bumps(self) -> tuple[SurfaceProfile | None, bool]:
        """(the bump profile, whether the stream has decided): decided once MIN_BUMP_PATH_MM of contact; a
        profile only when a period stands out of its local floor (bump_floor, choose_bump_period: the
        fitter remembers the period it last reported)."""
        profile, decided, _ = self._bump_fit()
        return profile, decided

    def _bump_fit(self) -> tuple[SurfaceProfile | None, bool, np.ndarray]:
        """bumps() and the phase coefficients β (2,) of the profile's period (zeros without a profile)."""
        if self._path_mm < MIN_BUMP_PATH_MM or self._bump_n < 4 * SEGMENT:
            return None, False, np.zeros(2)
        g = self._bump_g + 1e-12 * np.eye(2)[None]
        beta = np.linalg.solve(g, self._bump_b[..., None])[..., 0]  # (P, 2)
        explained = np.maximum(np.einsum("pi,pi->p", beta, self._bump_b), 0.0)
        floor = bump_floor(explained)[_BUMP_PAD:-_BUMP_PAD]  # the reported periods' (BUMP_PERIODS_MM)
        beta, explained = beta[_BUMP_PAD:-_BUMP_PAD], explained[_BUMP_PAD:-_BUMP_PAD]
        chosen = choose_bump_period(explained, floor, self._bump_kept)
        height = 0.0 if chosen is None else 2.0 * float(np.hypot(*beta[chosen]))  # β = (h/2)(cos, sin) of the phase
        if chosen is None or height < MIN_BUMP_MM:
            self._bump_kept = None
            return None, True, np.zeros(2)
        self._bump_kept = chosen
        return SurfaceProfile(height, float(BUMP_PERIODS_MM[chosen])), True, beta[chosen]

    def _with_other_dimensions(
        self,
        vibration: VibrationModel,
        prior: VibrationModel,
        decided: bool,
        bumps: SurfaceProfile | None,
        name: str,
        contact_s: float,
    ) -> VibrationModel:
        """`vibration` with the stream's friction, bumps (once decided; else the prior's) and taps (else the taps
        of the first prior this surface was fitted with), named and with its provenance."""
        if self._fallback_taps is None:
            # the library pick (the prior) can change window to window on one surface; each change would swap in
            # another texture's recorded taps (≈ 2.8 kB on the operators' link, a different contact feel) with no
            # new evidence about this surface, so its first prior's stand until the stream's own or a scene change
            self._fallback_taps = (prior.taps,)
        taps = self._fallback_taps[0]
        if self._taps:
            length = min(t.size for _, t in self._taps)
            speeds = np.array([s for s, _ in self._taps])
            taps = TapSet(speeds, local_mean_taps(speeds, np.array([t[:length] for _, t in self._taps])))
        return replace(
            vibration,
            name=name,
            mu=min(max(self.mu(prior.mu), 0.0), 4.99),
            taps=taps,
            surface=bumps if decided else prior.surface,
            provenance=f"learnt online from {contact_s:.1f} s of contact, prior {prior.name!r}",
        )

    def fit(
        self,
        prior: VibrationModel,
        name: str = "surface",
        prior_segments: float = PRIOR_SEGMENTS,
        keep_orders: tuple[int, int] | None = None,
    ) -> SurfaceFit:
        """The surface's model: the data where they are, the prior where they are thin. prior_segments: how many
        segments the prior counts as per grid point (> 0; near 0: the data alone wherever a segment fell);
        keep_orders: an earlier fit's (AR, MA) orders, kept unless clearly beaten (`choose_orders`; ignored when
        not in ORDERS)."""
        if not prior_segments > 0:
            raise ValueError(f"prior_segments must be > 0, got {prior_segments}")
        m = self.grid_speeds.size
        noise_psd, noise_source = self.noise()
        bumps, decided, beta = self._bump_fit()
        contact_s = self._contact_samples / self.rate_hz
        k = self.segments

        def keep_prior(status: FitStatus) -> SurfaceFit:
            return SurfaceFit(prior, status, np.zeros(m), 0, noise_psd, noise_source, contact_s)

        if k == 0:
            if self._slow >= MIN_SEGMENTS:
                return keep_prior(FitStatus.too_slow)
            return keep_prior(self._last_reason or FitStatus.no_contact)
        if k < MIN_SEGMENTS:
            return keep_prior(FitStatus.too_short)
        raw = self._raw[:k].astype(float)
        an = raw[:, 0]
        if bumps is not None:
            # the bumps' own acceleration, phase and all, comes off each segment: its line is tens of dB above
            # the texture's vibration and would leak through the taper's sidelobes over the whole band
            v, x = raw[:, 1], raw[:, 2]
            dv = np.gradient(v, axis=1) * self.rate_hz
            kk = 2 * np.pi / bumps.bump_period_mm
            c, sn = np.cos(kk * x), np.sin(kk * x)
            r1 = -1e-3 * (kk * kk * v * v * c + kk * dv * sn)
            r2 = -1e-3 * (-kk * kk * v * v * sn + kk * dv * c)
            an = an - (beta[0] * r1 + beta[1] * r2)
        y = (an - an.mean(axis=1, keepdims=True)) * self._taper
        rows = np.abs(np.fft.rfft(y, NFFT, axis=1)) ** 2 / (self.rate_hz * self._win_power)
        rows[:, 1:-1] *= 2.0
        band = (self.freqs >= BAND_HZ[0]) & (self.freqs < BAND_HZ[1])
        if noise_psd > 0 and float(np.median(rows[:, band].mean(axis=1))) < MIN_SNR * noise_psd:
            # the vibration is lost in the noise; friction, bumps and taps come from other signals and stand
            return SurfaceFit(
                self._with_other_dimensions(prior, prior, decided, bumps, name, contact_s),
                FitStatus.too_noisy,
                np.zeros(m),
                0,
                noise_psd,
                noise_source,
                contact_s,
                bumps=bumps,
            )
        if bumps is not None and bumps.bump_height_mm > 0:
            rows = _bridge_bump_lines(rows, self.freqs, self._vrange[:k], bumps.bump_period_mm)
        weights = np.zeros((k, m))
        np.put_along_axis(weights, self._idx[:k], self._w[:k], axis=1)
        # least squares in log power, as the renderer interpolates (LSFs blend like log spectra), with a ridge
        # towards the prior: (WᵀW + n₀I) L = Wᵀ(ln P + γ) + n₀ ln(S_prior + N), then S = e^L − N. A periodogram
        # bin is exponentially distributed about S + N, so E[ln P] = ln(S + N) − γ (Euler's γ).
        prior_psd = arma_psd(prior, self.grid_speeds, self.grid_forces, self.freqs)
        lhs = weights.T @ weights + prior_segments * np.eye(m)
        log_rows = np.log(np.maximum(rows, SPECTRUM_FLOOR)) + np.euler_gamma
        log_rows[:, [0, -1]] += np.log(2.0)  # DC and Nyquist are real: χ² with 1 dof, E[ln] = ln S − γ − ln 2
        # a prior silent somewhere (zero variance at a grid point) pulls towards the floor, not towards ln 0: a log
        # spectrum hundreds of nepers deep would drag the blend of a half-confident point into an unfittable one
        rhs = weights.T @ log_rows + prior_segments * np.log(np.maximum(prior_psd + noise_psd, SPECTRUM_FLOOR))
        spectra = np.exp(np.linalg.solve(lhs, rhs)) - noise_psd
        # below the noise floor the stream only bounds the surface from above: there the prior stands where it
        # lies below what was measured, and the measurement (at least NOISE_CLIP × the floor) where it does not
        hidden = spectra < noise_psd
        measured = np.maximum(spectra, NOISE_CLIP * noise_psd)
        spectra = np.where(hidden, np.minimum(prior_psd, measured), spectra)
        spectra = np.maximum(spectra, SPECTRUM_FLOOR)
        low = self.freqs < BAND_HZ[0]
        first = int(np.argmax(~low))
        spectra[:, low] = spectra[:, [first]]
        support = weights.sum(axis=0)
        confidence = support / (support + prior_segments)
        n_eff = (support + prior_segments) * HOP
        # each grid point's orders are judged where it was measured: above the noise floor
        vibration, (p, q) = self.grid_model(spectra, n_eff, band[None, :] & ~hidden, name, prior.mu, keep_orders)
        vibration = self._match_levels(vibration, weights, log_rows[:, band].mean(axis=1), noise_psd, prior_segments)
        order = p
        model = self._with_other_dimensions(vibration, prior, decided, bumps, name, contact_s)
        return SurfaceFit(
            model,
            FitStatus.ok,
            confidence,
            order,
            noise_psd,
            noise_source,
            contact_s,
            bumps=bumps,
            extra={"segments": k, "orders": [p, q]},
        )


def _bridge_bump_lines(rows: np.ndarray, freqs: np.ndarray, vrange: np.ndarray, period_mm: float) -> np.ndarray:
    """Each segment's periodogram with the bins its bump line swept (v_min/P … v_max/P Hz, one bin of slack)
    replaced by the log-linear bridge between their neighbours."""
    out = rows.copy()
    df = freqs[1] - freqs[0]
    lo = np.searchsorted(freqs, vrange[:, 0] / period_mm - df, side="left")
    hi = np.searchsorted(freqs, vrange[:, 1] / period_mm + df, side="right")
    for i in np.flatnonzero(hi > lo):
        a, b = max(int(lo[i]) - 1, 0), min(int(hi[i]), freqs.size - 1)
        if a == 0 and b == freqs.size - 1:
            continue
        left = out[i, a] if a > 0 or lo[i] > 0 else out[i, b]
        right = out[i, b] if b < freqs.size - 1 or hi[i] <= b else left
        t = (np.arange(a, b + 1) - a) / max(b - a, 1)
        out[i, a : b + 1] = np.exp((1 - t) * np.log(max(left, 1e-300)) + t * np.log(max(right, 1e-300)))
    return out


def with_name(fit: SurfaceFit, name: str) -> SurfaceFit:
    """The fit with its model renamed (a library entry's id)."""
    return replace(fit, model=replace(fit.model, name=name))
