"""The synthetic world: procedural textures with known physical parameters.

Each texture has physical parameters (micro-roughness, grain, macro bumps,
friction, stiffness, albedo). From them follow, by documented rules:
- a HaTT-style vibration model (ARMA over a speed × force grid), a macro surface
  profile (texture_library.surface) and tap transients,
- a grayscale photo-like image,
- ground-truth perceptual ratings (`true_ratings`) and rater-like noisy ratings.

The world is fair: every rating follows from a property that a stroking, tapping
tool with a camera can sense, as real perception does —

| rating          | physical cause        | what the sensors get                                               |
|-----------------|-----------------------|--------------------------------------------------------------------|
| rough–smooth    | roughness_um          | vibration level while stroking (ARMA variance ∝ roughness^1.4)     |
| flat–bumpy      | bump_height_mm        | position-periodic normal acceleration z''(x)·v² of the bump train  |
|                 |                       | (period bump_period_mm, 5–25 mm), read against position            |
| sticky–slippery | mu                    | tangential / normal force = μ (Coulomb friction against the motion)|
|                 |                       | and a stick–slip resonance in the vibration, sharper for higher μ  |
| hard–soft       | stiffness_n_per_mm    | tap transients (peak ∝ tap speed·√k, ringing at 90·k^0.35 Hz,      |
|                 |                       | decaying over 3–15 ms, longer when stiffer) and the stroke's       |
|                 |                       | contact resonance at 60·k^0.35 Hz                                  |

Grain, bump period and albedo change the signals and the image but no rating. The
camera sees every cue too (micro-texture contrast, shaded bumps, a sheen on slippery
surfaces, fibres on soft ones), as a photo would.

The world is the project's own data: the demo and every test that must not
depend on ../shared run on it. The mapping from parameters to ratings is the
"known answer" that evaluation on this world must recover. Everything is drawn
from seeded generators: the same seed gives the same world.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.signal import lfilter

from texture_library.attributes import ATTRIBUTES
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.surface import SurfaceProfile
from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel

#: bumped whenever the world's physics change: datasets record it, demo assets of another version are rebuilt
WORLD_VERSION = 2
RATE_HZ = 1000.0
GRID_MAX_SPEED = 350.0  # mm/s
GRID_MAX_FORCE = 5.0  # N
PX_PER_MM = 10.0

#: parameter ranges (low, high) and whether they are drawn log-uniformly
PARAM_RANGES: dict[str, tuple[float, float, bool]] = {
    "roughness_um": (1.0, 200.0, True),  # RMS height of the micro-texture
    "grain_mm": (0.3, 3.0, True),  # spatial period of the micro-texture
    "bump_height_mm": (0.0, 1.5, False),  # height of macro bumps
    "bump_period_mm": (
        5.0,
        25.0,
        True,
    ),  # spacing of macro bumps: felt against position (at 150 mm/s they ring at 6–30 Hz)
    "mu": (0.15, 1.2, False),  # kinetic friction coefficient
    "stiffness_n_per_mm": (0.05, 50.0, True),  # contact stiffness
    "albedo": (0.25, 0.75, False),  # mean grey level: perceptually irrelevant on purpose
}


@dataclass(frozen=True)
class PhysicalParams:
    roughness_um: float
    grain_mm: float
    bump_height_mm: float
    bump_period_mm: float
    mu: float
    stiffness_n_per_mm: float
    albedo: float

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def sample_params(rng: np.random.Generator) -> PhysicalParams:
    """Draw one texture's parameters from PARAM_RANGES."""
    values = {}
    for name, (lo, hi, log) in PARAM_RANGES.items():
        values[name] = float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if log else float(rng.uniform(lo, hi))
    return PhysicalParams(**values)


def _unit_log(x: float, name: str) -> float:
    lo, hi, _ = PARAM_RANGES[name]
    return float(np.clip((np.log(x) - np.log(lo)) / (np.log(hi) - np.log(lo)), 0.0, 1.0))


# ---- ground truth --------------------------------------------------------------------------------
def true_ratings(p: PhysicalParams) -> np.ndarray:
    """The documented mapping from physics to bipolar ratings (4,), −100…100.

        rough_smooth    = −100·tanh(1.0·log10(roughness_um / 15))     rougher → −100
        flat_bumpy      = +100·tanh(1.5·(bump_height_mm − 0.5))        higher bumps → +100
        sticky_slippery = −100·tanh(2.0·(mu − 0.6))                    more friction → −100
        hard_soft       = −100·tanh(0.9·log10(stiffness_n_per_mm / 1)) stiffer → −100
    Slopes are gentle enough that ratings spread over the scale instead of piling up at ±100.
    """
    return 100.0 * np.array(
        [
            -np.tanh(1.0 * np.log10(p.roughness_um / 15.0)),
            np.tanh(1.5 * (p.bump_height_mm - 0.5)),
            -np.tanh(2.0 * (p.mu - 0.6)),
            -np.tanh(0.9 * np.log10(p.stiffness_n_per_mm / 1.0)),
        ]
    )


def rater_ratings(
    truth: np.ndarray, n_raters: int, rng: np.random.Generator, *, bias_std: float = 6.0, noise_std: float = 10.0
) -> np.ndarray:
    """Noisy integer ratings (n_raters, 4): truth + a per-rater bias + per-rating noise, clipped to ±100."""
    if n_raters < 1:
        raise ValueError(f"n_raters must be ≥ 1, got {n_raters}")
    bias = rng.normal(0.0, bias_std, size=(n_raters, 1))
    noisy = truth[None, :] + bias + rng.normal(0.0, noise_std, size=(n_raters, len(ATTRIBUTES)))
    return np.clip(np.round(noisy), -100, 100)


def material_group(p: PhysicalParams) -> str:
    """A coarse group label (for per-group error tables), by rule."""
    soft = p.stiffness_n_per_mm < 0.5
    if soft and p.roughness_um > 20:
        return "fabric"
    if soft:
        return "foam"
    if p.stiffness_n_per_mm > 10 and p.roughness_um < 10:
        return "metal"
    if p.stiffness_n_per_mm > 10:
        return "stone"
    if p.mu > 0.7:
        return "rubber"
    return "plastic" if p.roughness_um < 20 else "paper"


# ---- vibration ----------------------------------------------------------------------------------
def _contact_hz(p: PhysicalParams) -> float:
    """Tool–surface contact resonance: stiffer surfaces ring higher (≈ √k scaling, clipped)."""
    return float(np.clip(60.0 * p.stiffness_n_per_mm**0.35, 25.0, 460.0))


#: a second-order high-pass at ≈ 20 Hz shared by every grid point (double zero at z = 0.99, double
#: pole at z = 0.88): like HaTT's models, fitted to recordings high-passed at 20 Hz, texture
#: vibration carries little below 20 Hz — that band belongs to the hand's motion and the bumps
HIGHPASS_MA = np.array([1.0, -1.98, 0.9801])
HIGHPASS_AR = np.array([1.0, -1.76, 0.7744])


def _arma_at(p: PhysicalParams, speed: float, force: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(AR poly (9,), MA poly (3,), excitation variance) at one grid point.

    Three resonances: the micro-texture at v/grain, the tool–surface contact resonance (higher
    and sharper for stiffer surfaces) and stick–slip at half the contact resonance (sharper for
    more friction), behind the 20 Hz high-pass. The RMS level is set by roughness, speed and
    force. Macro bumps are not noise: they are the deterministic surface profile
    (texture_library.surface) that the stroke renders on top.
    """
    v = max(speed, 1.0)
    contact = _contact_hz(p)
    freqs = np.clip([v / p.grain_mm, contact, 0.5 * contact + 10.0], 8.0, 460.0)
    radii = np.array(
        [
            0.90,
            0.75 + 0.20 * _unit_log(p.stiffness_n_per_mm, "stiffness_n_per_mm"),
            0.60 + 0.35 * (p.mu - PARAM_RANGES["mu"][0]) / (PARAM_RANGES["mu"][1] - PARAM_RANGES["mu"][0]),
        ]
    )
    ar = np.convolve(poles_to_poly(freqs, radii, RATE_HZ), HIGHPASS_AR)
    ma = HIGHPASS_MA
    if speed <= 0.0 or force <= 0.0:
        return ar, ma, 0.0
    rms = (p.roughness_um / 30.0) ** 0.7 * (speed / 150.0) ** 0.8 * (force / 2.0) ** 0.5
    impulse = np.zeros(2048)
    impulse[0] = 1.0
    power_gain = float(np.sum(lfilter(ma, ar, impulse) ** 2))
    return ar, ma, rms**2 / power_gain


def vibration_model(p: PhysicalParams, name: str, rng: np.random.Generator, grid: int = 5) -> VibrationModel:
    """The texture's vibration model on a grid × grid speed–force lattice (two triangles per cell),
    with its bump profile and tap transients."""
    speeds_1d = np.linspace(0.0, GRID_MAX_SPEED, grid)
    forces_1d = np.linspace(0.0, GRID_MAX_FORCE, grid)
    ss, ff = np.meshgrid(speeds_1d, forces_1d, indexing="ij")
    speeds, forces = ss.ravel(), ff.ravel()
    ar_lsf, ma_lsf, variance = [], [], []
    for s, f in zip(speeds, forces):
        ar, ma, var = _arma_at(p, s, f)
        ar_lsf.append(poly_to_lsf(ar))
        ma_lsf.append(poly_to_lsf(ma))
        variance.append(var)
    tris = []
    for i in range(grid - 1):
        for j in range(grid - 1):
            a, b, c, d = i * grid + j, (i + 1) * grid + j, i * grid + j + 1, (i + 1) * grid + j + 1
            tris += [(a, b, c), (b, d, c)]
    return VibrationModel(
        name=name,
        speeds=speeds,
        forces=forces,
        triangles=np.array(tris),
        ar_lsf=np.array(ar_lsf),
        ma_lsf=np.array(ma_lsf),
        variance=np.array(variance),
        gain=np.ones(speeds.size),
        mu=p.mu,
        max_speed=GRID_MAX_SPEED,
        max_force=GRID_MAX_FORCE,
        taps=tap_transients(p, rng),
        rate_hz=RATE_HZ,
        provenance="hapticlink synthetic world (procedural, generated)",
        extra={"physical": p.to_dict()},
        surface=SurfaceProfile(p.bump_height_mm, p.bump_period_mm),
    )


def tap_transients(p: PhysicalParams, rng: np.random.Generator, n_taps: int = 10, n: int = 100) -> TapSet:
    """n_taps taps of n samples (1 kHz) at speeds 5–80 mm/s, like HaTT's: a decaying oscillation at
    1.5 × the contact resonance starting 5 ms in, peak 0.2·speed·√k m/s², time constant
    3–15 ms (log-stiffness), plus 0.05 m/s² sensor noise. Harder surfaces ring higher, louder, longer."""
    speeds = np.sort(rng.uniform(5.0, 80.0, n_taps))
    t = np.arange(n) / RATE_HZ
    f = 1.5 * _contact_hz(p)
    tau = 0.003 + 0.012 * _unit_log(p.stiffness_n_per_mm, "stiffness_n_per_mm")
    amp = 0.2 * speeds[:, None] * np.sqrt(p.stiffness_n_per_mm)
    onset = 5
    shape = np.where(
        t >= onset / RATE_HZ, np.exp(-(t - onset / RATE_HZ) / tau) * np.sin(2 * np.pi * f * (t - onset / RATE_HZ)), 0.0
    )
    return TapSet(speeds, amp * shape[None, :] + 0.05 * rng.standard_normal((n_taps, n)))


# ---- image --------------------------------------------------------------------------------------
def _bandpass_noise(
    shape: tuple[int, int], period_px: float, rng: np.random.Generator, bandwidth: float = 0.5
) -> np.ndarray:
    """Gaussian noise band-passed around spatial frequency 1/period_px (unit std)."""
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.rfftfreq(shape[1])[None, :]
    k = np.hypot(kx, ky)
    k0 = 1.0 / max(period_px, 2.0)
    mask = np.exp(-0.5 * (np.log(np.maximum(k, 1e-6) / k0) / bandwidth) ** 2)
    field = np.fft.irfft2(np.fft.rfft2(rng.standard_normal(shape)) * mask, s=shape)
    return field / max(field.std(), 1e-12)


def render_image(p: PhysicalParams, rng: np.random.Generator, size: int = 448) -> np.ndarray:
    """A grayscale image (size, size) uint8 of the texture seen from above at PX_PER_MM, lit from the left.

    Visual cues, by design: micro-texture contrast ∝ log roughness at the grain's scale; macro
    bumps shaded by their slope; a specular sheen for slippery (low-μ) surfaces; a faint fibrous
    streak pattern for soft surfaces — hardness is the attribute photos explain least.
    """
    if size < 32:
        raise ValueError(f"image size must be ≥ 32 px, got {size}")
    shape = (size, size)
    yy, xx = np.mgrid[0:size, 0:size] / PX_PER_MM  # mm
    theta = rng.uniform(0, np.pi)
    u = np.cos(theta) * xx + np.sin(theta) * yy
    w = -np.sin(theta) * xx + np.cos(theta) * yy
    k_b = 2 * np.pi / p.bump_period_mm
    height = p.bump_height_mm * 0.25 * (1 + np.cos(k_b * u)) * (1 + np.cos(k_b * w + rng.uniform(0, 2 * np.pi)))
    slope_x = np.gradient(height, axis=1) * PX_PER_MM  # mm/mm
    img = p.albedo + 0.35 * np.tanh(slope_x)
    micro = _bandpass_noise(shape, p.grain_mm * PX_PER_MM, rng)
    img += 0.05 * (1.0 + np.log10(p.roughness_um)) * micro
    sheen = np.exp(-(((xx - rng.uniform(10, 30)) ** 2 + (yy - rng.uniform(10, 30)) ** 2) / (2 * 12.0**2)))
    img += 0.4 * max(0.0, 0.8 - p.mu) * sheen
    softness = 1.0 - _unit_log(p.stiffness_n_per_mm, "stiffness_n_per_mm")
    fibres = _bandpass_noise(shape, 6.0, rng, bandwidth=0.3)
    fibres = np.fft.irfft(np.fft.rfft(fibres, axis=0) * np.exp(-np.fft.rfftfreq(size)[:, None] * 40), n=size, axis=0)
    img += 0.08 * softness * fibres / max(fibres.std(), 1e-12)
    return (np.clip(img, 0.0, 1.0) * 255).round().astype(np.uint8)


@dataclass(frozen=True)
class SyntheticTexture:
    """One texture of the synthetic world with everything derived from its parameters."""

    texture_id: str
    params: PhysicalParams
    group: str
    model: VibrationModel
    image: np.ndarray
    truth: np.ndarray
    ratings: np.ndarray  # (n_raters, 4)


def make_world(n_textures: int, seed: int = 0, *, n_raters: int = 12, image_size: int = 448) -> list[SyntheticTexture]:
    """n_textures procedural textures, reproducible from seed."""
    if n_textures < 1:
        raise ValueError(f"n_textures must be ≥ 1, got {n_textures}")
    root = np.random.default_rng(seed)
    world = []
    for i in range(n_textures):
        rng = np.random.default_rng(root.integers(2**63))
        p = sample_params(rng)
        tid = f"synth_{i:03d}"
        truth = true_ratings(p)
        world.append(
            SyntheticTexture(
                texture_id=tid,
                params=p,
                group=material_group(p),
                model=vibration_model(p, tid, rng),
                image=render_image(p, rng, image_size),
                truth=truth,
                ratings=rater_ratings(truth, n_raters, rng),
            )
        )
    return world
