"""What the operator feels: selection rules scored leave-one-texture-out (the rules: docs/models.md, fidelity).

For each stroked texture the library holds every other texture. A rule's pick is compared with the
stroked texture on its true ratings, its exact vibration spectrum (`texture_library.spectrum`), a
sensitivity-weighted spectrum (`texture_library.vibrotactile`) and its friction μ. Per-window rules
(physical, physical-lsd, hybrid) pick once per window of the stroked texture's recording, as the
service would; a texture's figure is the mean over its windows. The hybrid's weight is chosen inside
each outer fold on its training textures only (nested).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.evaluation.bootstrap import bootstrap_mean
from models.tactile.config import TactileConfig
from models.tactile.preprocess import TactilePreprocessor
from texture_library.attributes import ATTRIBUTES, REPORT_SCALE
from texture_library.selection import SpectralTable
from texture_library.spectrum import band_frequencies, log_spectral_distance_db, model_spectra, pooled_distance_db
from texture_library.vibration import VibrationModel
from texture_library.vibrotactile import sensitivity_weights

#: the hybrid's weight grid (rating units per dB) and its tuning objective's targets (docs/models.md)
WEIGHTS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
RATING_TARGET = 5.5
SPECTRAL_TARGET_DB = 6.0
WINDOWS_PER_TEXTURE = 24
METRICS = (
    "rating_distance",
    "spectral_distance_db",
    "pooled_spectral_distance_db",
    "weighted_spectral_distance_db",
    "mu_difference",
)


@dataclass(frozen=True)
class World:
    """Everything the rules and the metrics read, for T textures.

    truth, predicted: (T, 4) bipolar; rating_d, spectral_d, pooled_d, weighted_d, mu_d: (T, T) pairwise metrics
    (0–100 scale, dB, dB, dB, |Δμ|; pooled_d: `texture_library.spectrum.pooled_distance_db`); perceptual_d:
    (T, T) bipolar distance from texture i's estimated ratings
    to texture j's true ratings; whittle, lsd: (T, W, T) window w of texture i against model j, dB;
    whittle_bare: the same as whittle against the bare model spectra, without the sensor's noise floor
    (the physical rule as first written down, kept to show what the noise floor changed)."""

    name: str
    textures: list[str]
    truth: np.ndarray
    predicted: np.ndarray
    rating_d: np.ndarray
    spectral_d: np.ndarray
    pooled_d: np.ndarray
    weighted_d: np.ndarray
    mu_d: np.ndarray
    perceptual_d: np.ndarray
    whittle: np.ndarray
    lsd: np.ndarray
    whittle_bare: np.ndarray

    def metrics(self) -> dict[str, np.ndarray]:
        return {
            "rating_distance": self.rating_d,
            "spectral_distance_db": self.spectral_d,
            "pooled_spectral_distance_db": self.pooled_d,
            "weighted_spectral_distance_db": self.weighted_d,
            "mu_difference": self.mu_d,
        }


def load_world(dataset: str | Path, predictions: str | Path, windows: int = WINDOWS_PER_TEXTURE) -> World:
    """The rated textures of `dataset` that `predictions` (a results.json of `hapticlink evaluate`) holds;
    `windows` per texture (fewer when a recording is shorter: the shortest sets the count for all)."""
    ds = Dataset(dataset)
    pred = json.loads(Path(predictions).read_text())["predictions"]
    means = ds.mean_ratings()
    textures = [t for t in ds.texture_ids("yes") if t in pred]
    if len(textures) < 3:
        raise ValueError(f"{dataset}: only {len(textures)} rated textures have predictions in {predictions}")
    truth = np.array([means[t] for t in textures], float)
    if not np.all(np.isfinite(truth)):
        raise ValueError(f"{dataset}: a rated texture lacks a mean rating on some attribute")
    predicted = np.array([[pred[t][a] for a in ATTRIBUTES] for t in textures], float)
    models = []
    for t in textures:
        path = ds.vibration_model_path(t)
        if path is None:
            raise ValueError(f"{dataset}: texture {t!r} has no vibration model")
        models.append(VibrationModel.load(path))
    spectra = np.array([model_spectra(m) for m in models])  # (T, 9, n)
    weights = sensitivity_weights(band_frequencies())
    log_s = 10.0 * np.log10(np.maximum(spectra, 1e-12))
    T = len(textures)
    spectral_d = np.zeros((T, T))
    pooled_d = np.zeros((T, T))
    weighted_d = np.zeros((T, T))
    for i in range(T):
        spectral_d[i] = log_spectral_distance_db(np.broadcast_to(spectra[i], spectra.shape), spectra).mean(axis=1)
        pooled_d[i] = pooled_distance_db(np.broadcast_to(spectra[i], spectra.shape), spectra)
        diff2 = (log_s[i][None] - log_s) ** 2  # (T, 9, n)
        weighted_d[i] = np.sqrt((diff2 * weights).sum(axis=-1) / weights.sum()).mean(axis=1)
    mu = np.array([m.mu for m in models])
    table = SpectralTable(textures, models)
    bare = SpectralTable(textures, models, noise_psd=0.0)
    config = TactileConfig()
    per_texture = [_windows(ds, t, config) for t in textures]
    windows = min(windows, *(len(s) for _, s, _ in per_texture))  # the same count for every texture
    whittle = np.zeros((T, windows, T))
    lsd = np.zeros((T, windows, T))
    whittle_bare = np.zeros((T, windows, T))
    for i, (accel, speed, force) in enumerate(per_texture):
        keep = np.linspace(0, len(speed) - 1, windows).round().astype(int)
        accel, speed, force = accel[keep], speed[keep], force[keep]
        for w in range(windows):
            whittle[i, w] = table.mismatch_db(accel[w], float(speed[w]), float(force[w]), "whittle")
            lsd[i, w] = table.mismatch_db(accel[w], float(speed[w]), float(force[w]), "lsd")
            whittle_bare[i, w] = bare.mismatch_db(accel[w], float(speed[w]), float(force[w]), "whittle")
    return World(
        name=ds.name,
        textures=textures,
        truth=truth,
        predicted=predicted,
        rating_d=np.abs(truth[:, None, :] - truth[None, :, :]).mean(axis=-1) * REPORT_SCALE,
        spectral_d=spectral_d,
        pooled_d=pooled_d,
        weighted_d=weighted_d,
        mu_d=np.abs(mu[:, None] - mu[None, :]),
        perceptual_d=np.linalg.norm(predicted[:, None, :] - truth[None, :, :], axis=-1),
        whittle=whittle,
        lsd=lsd,
        whittle_bare=whittle_bare,
    )


def _windows(ds: Dataset, texture: str, config: TactileConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The windows of the texture's first recording as the service's preprocessor makes them:
    accel (n, L, k) m/s², mean speed (n,) mm/s, mean normal force (n,) N."""
    rec = ds.recordings(texture)[0]
    pre = TactilePreprocessor(config, max_buffer_s=None)
    pre.push(accel=rec.accel, force=rec.force, speed=rec.speed, position=rec.position)
    pre.flush()
    batch = pre.take()
    if len(batch) == 0:
        raise ValueError(f"texture {texture!r}: its recording holds no complete window")
    normal = batch.force[..., 0] if batch.force.ndim == 3 else batch.force
    return batch.accel, batch.speed.mean(axis=1), normal.mean(axis=1)


# ---- rules: per stroked texture i, its pick(s) from a library (a boolean mask over textures) ----------
def _window_picks(costs: np.ndarray, library: np.ndarray) -> np.ndarray:
    """costs (..., T) → argmin over the library's entries (...,)."""
    return np.where(library, costs, np.inf).argmin(axis=-1)


def _score_picks(world: World, stroked: np.ndarray, picks: np.ndarray) -> dict[str, np.ndarray]:
    """Per stroked texture, each metric averaged over its picks. stroked: (k,), picks: (k,) or (k, W)."""
    p = picks if picks.ndim == 2 else picks[:, None]
    return {name: m[stroked[:, None], p].mean(axis=1) for name, m in world.metrics().items()}


def hybrid_costs(world: World, i: int, weight: float) -> np.ndarray:
    """(W, T) hybrid cost of every window of texture i against every entry."""
    return world.perceptual_d[i][None, :] + weight * world.whittle[i]


def tune_weight(world: World, train: np.ndarray) -> tuple[float, list[dict]]:
    """The hybrid weight chosen on the textures in `train` (bool mask) only: each stroked in turn with the
    library holding the other training textures; the lowest max(rating/5.5, spectral/6.0), a tie to the
    smaller weight. Returns (weight, the grid's inner scores)."""
    inner = np.flatnonzero(train)
    rows = []
    for weight in WEIGHTS:
        picks = np.empty((inner.size, world.whittle.shape[1]), int)
        for k, j in enumerate(inner):
            library = train.copy()
            library[j] = False
            picks[k] = _window_picks(hybrid_costs(world, int(j), weight), library)
        s = _score_picks(world, inner, picks)
        rd, sd = float(s["rating_distance"].mean()), float(s["spectral_distance_db"].mean())
        rows.append(
            {
                "weight": weight,
                "rating_distance": rd,
                "spectral_distance_db": sd,
                "score": max(rd / RATING_TARGET, sd / SPECTRAL_TARGET_DB),
            }
        )
    best = min(range(len(rows)), key=lambda k: (round(rows[k]["score"], 12), WEIGHTS[k]))
    return WEIGHTS[best], rows


def run_rules(world: World) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    """Per rule, per metric, (T,) per-texture values; and the hybrid's per-fold weights."""
    T = len(world.textures)
    out: dict[str, dict[str, np.ndarray]] = {}
    per_rule_picks: dict[str, list[np.ndarray]] = {r: [] for r in RULE_ORDER if r != "random"}
    fold_weights = []
    true_perceptual = np.linalg.norm(world.truth[:, None, :] - world.truth[None, :, :], axis=-1)
    for i in range(T):
        library = np.ones(T, bool)
        library[i] = False
        per_rule_picks["perceptual"].append(np.array([_window_picks(world.perceptual_d[i], library)]))
        per_rule_picks["oracle-perceptual"].append(np.array([_window_picks(true_perceptual[i], library)]))
        per_rule_picks["oracle-spectral"].append(np.array([_window_picks(world.spectral_d[i], library)]))
        per_rule_picks["physical"].append(_window_picks(world.whittle[i], library))
        per_rule_picks["physical-lsd"].append(_window_picks(world.lsd[i], library))
        per_rule_picks["physical-no-noise-floor"].append(_window_picks(world.whittle_bare[i], library))
        weight, _ = tune_weight(world, library)  # the outer texture is neither stroked nor in the library here
        fold_weights.append(weight)
        per_rule_picks["hybrid"].append(_window_picks(hybrid_costs(world, i, weight), library))
    for rule, picks in per_rule_picks.items():
        out[rule] = {
            name: np.array([m[i, p].mean() for i, p in enumerate(picks)]) for name, m in world.metrics().items()
        }
    off = ~np.eye(T, dtype=bool)
    out["random"] = {name: (m * off).sum(axis=1) / (T - 1) for name, m in world.metrics().items()}
    served_weight, served_grid = tune_weight(world, np.ones(T, bool))
    return out, {"fold_weights": fold_weights, "served_weight": served_weight, "served_grid": served_grid}


RULE_ORDER = (
    "perceptual",
    "random",
    "oracle-perceptual",
    "oracle-spectral",
    "physical",
    "physical-lsd",
    "hybrid",
    "physical-no-noise-floor",
)


def self_rank(mismatch: np.ndarray) -> float:
    """Median rank (1 = first) of a stroked texture's own model among all T by a window mismatch (T, W, T)."""
    T = mismatch.shape[0]
    own = mismatch[np.arange(T), :, np.arange(T)]  # (T, W)
    return float(np.median((mismatch < own[:, :, None]).sum(axis=-1) + 1))


def summarise(world: World, per_texture: dict[str, dict[str, np.ndarray]], seed: int = 0) -> list[dict]:
    """One row per rule: each metric's mean over textures and its texture-level bootstrap 95 % interval."""
    rows = []
    for rule in RULE_ORDER:
        vals = per_texture[rule]
        ci = {name: bootstrap_mean(vals[name], seed=seed) for name in METRICS}
        rows.append(
            {
                "rule": rule,
                **{name: round(ci[name]["mean"], 4) for name in METRICS},
                "textures": len(world.textures),
                "ci95": {name: [round(ci[name]["lo"], 4), round(ci[name]["hi"], 4)] for name in METRICS},
            }
        )
    return rows


def meets_targets(row: dict) -> bool:
    return row["spectral_distance_db"] <= SPECTRAL_TARGET_DB and row["rating_distance"] <= RATING_TARGET
