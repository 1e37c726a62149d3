"""Estimators evaluated by leave-one-texture-out: each fits on training textures only.

Everything learnt from data — standardisation, PCA, hyper-parameters picked by
inner cross-validation, early stopping — is fit inside `fit`, on the textures
it is given, so a held-out texture can never leak into its own prediction.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Literal

import numpy as np

from models.inference.standardize import Z_CLIP, Standardizer
from models.offline.evaluation.data import TextureData
from models.visual.pooling import pool_texture_views
from texture_library.attributes import RATING_MAX, RATING_MIN

Modality = Literal["none", "tactile", "visual", "both"]


class Estimator(ABC):
    """fit(training textures) → predict(textures) → (T, 4) bipolar ratings."""

    name: str = "estimator"
    modality: Modality = "none"

    @abstractmethod
    def fit(self, data: TextureData, seed: int) -> Estimator: ...

    @abstractmethod
    def predict(self, data: TextureData) -> np.ndarray: ...

    def predict_windows(self, data: TextureData) -> list[np.ndarray]:
        """Per texture, (n_i, 4) bipolar answers to its n_i tactile windows, before the output clip: what the
        exported graph answers window by window (composites such as `selected` and the mean of kernel models
        combine their members' windows). A model that answers once per texture has none."""
        raise NotImplementedError(f"{self.name} answers once per texture; it has no per-window answers")

    def n_params(self) -> int:
        return 0

    def fit_info(self) -> dict:
        """What the fit chose (hyper-parameters, epochs): reported per fold."""
        return {}

    def pooled_views(self, stored: int) -> int:
        """How many of a texture's `stored` image views this model pools into its visual input (view 0 first)."""
        return 1


def union_modality(modalities) -> Modality:
    """The inputs a composite model reads, from its members' modalities."""
    seen = set(modalities)
    has_v = bool(seen & {"visual", "both"})
    has_t = bool(seen & {"tactile", "both"})
    return "both" if has_v and has_t else "visual" if has_v else "tactile" if has_t else "none"


def window_mean(windows: list[np.ndarray]) -> np.ndarray:
    """(T, 4): per texture the mean of its windows' answers (n_i, 4), each clipped to the rating range
    first — as the exported graph clips every window's output before the service averages them."""
    return np.stack([np.clip(w, RATING_MIN, RATING_MAX).mean(axis=0) for w in windows])


def common_views(models) -> int | None:
    """The number of image views the members pool (None: none reads images); one model file records one."""
    views = {getattr(m, "views", None) for m in models} - {None}
    if len(views) > 1:
        raise ValueError(f"members pool different numbers of views {sorted(views)}; a model file records one")
    return views.pop() if views else None


# ---- texture-level design matrices --------------------------------------------------------------
def tactile_summary(data: TextureData, stats: tuple[str, ...] = ("mean",)) -> np.ndarray:
    """(T, F·len(stats)): per-texture statistics of its window features."""
    funcs = {"mean": np.mean, "std": np.std}
    return np.stack([np.concatenate([funcs[s](w, axis=0) for s in stats]) for w in data.tactile]).astype(np.float64)


def tactile_groups(data: TextureData) -> list[slice]:
    """Column slices of the tactile feature groups (TactileConfig.group_slices: the base set, then each
    extra group), or one slice over every column when the data does not name its configuration."""
    width = data.tactile[0].shape[1]
    if "tactile_config" not in data.meta:
        return [slice(0, width)]
    from models.tactile.config import TactileConfig

    slices = list(TactileConfig(**data.meta["tactile_config"]).group_slices().values())
    if slices[-1].stop != width:
        raise ValueError(f"tactile features have {width} columns, their configuration says {slices[-1].stop}")
    return slices


def tactile_blocks(data: TextureData, stats: tuple[str, ...] = ("mean",)) -> list[np.ndarray]:
    """tactile_summary split into one block per feature group, each with its columns of every statistic."""
    summary = tactile_summary(data, stats)
    width = data.tactile[0].shape[1]
    return [
        np.concatenate([summary[:, k * width + g.start : k * width + g.stop] for k in range(len(stats))], axis=1)
        for g in tactile_groups(data)
    ]


def visual_matrix(data: TextureData, view: int = 0) -> np.ndarray:
    """(T, D): one view of each texture's image (view 0 is the original)."""
    if data.visual is None:
        raise ValueError("this estimator needs visual features, but the data has none")
    return data.visual[:, view, :].astype(np.float64)


def pooled_visual(data: TextureData, views: int) -> np.ndarray:
    """(T, D): each texture's first `views` views pooled (models.visual.pooling), as the service pools frames."""
    if data.visual is None:
        raise ValueError("this estimator needs visual features, but the data has none")
    return pool_texture_views(data.visual, views).astype(np.float64)


class TextureFeatures:
    """Builds the standardised design matrix of a modality; blocks are weighted so each block
    carries equal total variance in a fusion (otherwise the larger block dominates). The blocks
    are the visual vector and each tactile feature group (the 526 MFCC features and statistics
    are one group; friction, spatial and taps are one each), so two friction columns weigh as
    much as 526 MFCC columns."""

    def __init__(self, modality: Modality, tactile_stats: tuple[str, ...] = ("mean",), views: int = 1):
        if modality not in ("tactile", "visual", "both"):
            raise ValueError(f"modality must be tactile, visual or both, got {modality!r}")
        if views < 1:
            raise ValueError(f"views must be ≥ 1, got {views}")
        self.modality = modality
        self.tactile_stats = tactile_stats
        self.views = views  # image views pooled per texture (1: the original photo only)

    def _blocks(self, data: TextureData, view: int | None = None) -> list[np.ndarray]:
        """view None: the first `views` views pooled; an int: that one view (training on every view)."""
        blocks = []
        if self.modality in ("visual", "both"):
            blocks.append(pooled_visual(data, self.views) if view is None else visual_matrix(data, view))
        if self.modality in ("tactile", "both"):
            blocks += tactile_blocks(data, self.tactile_stats)
        return blocks

    def fit_transform(self, data: TextureData) -> np.ndarray:
        blocks = self._blocks(data)
        self.scalers = [Standardizer().fit(b) for b in blocks]
        return self._combine(blocks)

    def fit_transform_views(self, data: TextureData) -> tuple[np.ndarray, np.ndarray]:
        """One row per (texture, augmented image view): (X (T·V, K), texture index (T·V,)).

        Training on every view teaches invariance to rotation, flips and noise; prediction
        still uses the original view only, as the service sees one camera frame."""
        n_views = 1 if data.visual is None or self.modality == "tactile" else data.visual.shape[1]
        per_view = [self._blocks(data, v if n_views > 1 else None) for v in range(n_views)]
        stacked = [np.concatenate(parts) for parts in zip(*per_view)]
        self.scalers = [Standardizer().fit(b) for b in stacked]
        return self._combine(stacked), np.tile(np.arange(len(data)), n_views)

    def transform(self, data: TextureData) -> np.ndarray:
        return self._combine(self._blocks(data))

    def _combine(self, blocks: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([s.transform(b) / np.sqrt(b.shape[1]) for s, b in zip(self.scalers, blocks)], axis=1)


def require_targets(data: TextureData) -> np.ndarray:
    if data.targets is None:
        raise ValueError("fit needs rated textures (targets), got none")
    return data.targets.astype(np.float64)


# ---- estimators ---------------------------------------------------------------------------------
class MeanEstimator(Estimator):
    """Predict-the-mean: the training textures' mean rating for every texture."""

    name = "mean"

    def fit(self, data: TextureData, seed: int) -> MeanEstimator:
        self.mean = require_targets(data).mean(axis=0)
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        return np.tile(self.mean, (len(data), 1))

    def n_params(self) -> int:
        return 4


def _repeated_rows(names: list[str]) -> list[np.ndarray] | None:
    """The row indices of each texture name, when some name repeats; None when every row is its own texture."""
    if len(set(names)) == len(names):
        return None
    rows: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        rows.setdefault(name, []).append(i)
    return [np.array(r) for r in rows.values()]


class RidgeEstimator(Estimator):
    """Ridge regression on texture-level features; α by efficient leave-one-out over the training textures.

    Rows that share a texture name (augmented copies of one texture, `tradeoffs.study`) leave out together: a copy
    left out beside its near-twins would make a weak α look good."""

    def __init__(
        self,
        modality: Modality,
        alphas: np.ndarray | None = None,
        tactile_stats: tuple[str, ...] = ("mean",),
        views: int = 1,
    ):
        self.modality = modality
        self.name = f"ridge-{modality}"
        self.features = TextureFeatures(modality, tactile_stats, views)
        self.views = views
        self.alphas = np.logspace(-3, 4, 29) if alphas is None else np.asarray(alphas)

    def fit(self, data: TextureData, seed: int) -> RidgeEstimator:
        X = self.features.fit_transform(data)
        y = require_targets(data)
        self.y_mean = y.mean(axis=0)
        yc = y - self.y_mean
        # LOO residuals of ridge in closed form via the SVD of X (n ≪ d here).
        u, s, vt = np.linalg.svd(X, full_matrices=False)
        uty = u.T @ yc
        groups = _repeated_rows(data.textures)
        best = (np.inf, None)
        for a in self.alphas:
            d = s**2 / (s**2 + a)
            fitted = yc - u @ (d[:, None] * uty)
            if groups is None:
                # the fitted intercept adds 1/n to every leverage (columns of X are centred)
                hat_diag = np.sum(u**2 * d, axis=1) + 1.0 / len(yc)
                resid = fitted / (1 - hat_diag)[:, None]
            else:  # leave a texture's rows out together: r_g = (I − H_gg)⁻¹ e_g, H with the intercept's 1/n
                resid = np.empty_like(fitted)
                for rows in groups:
                    h = (u[rows] * d) @ u[rows].T + 1.0 / len(yc)
                    resid[rows] = np.linalg.solve(np.eye(len(rows)) - h, fitted[rows])
            loss = float(np.mean(resid**2))
            if loss < best[0]:
                best = (loss, a)
        self.alpha = float(best[1])
        self.coef = vt.T @ ((s / (s**2 + self.alpha))[:, None] * uty)
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        return self.features.transform(data) @ self.coef + self.y_mean

    def n_params(self) -> int:
        return int(self.coef.size + self.y_mean.size)

    def fit_info(self) -> dict:
        return {"alpha": self.alpha}

    def pooled_views(self, stored: int) -> int:
        return self.views

    def add_graph(self, g) -> str:
        """The per-window model into a models.offline.onnx_graph.GraphBuilder; returns its (N, 4) output. Linear
        (within the z-clip), so averaging window predictions equals predicting from the texture's mean
        window — the texture-level fit serves window by window."""
        if self.features.tactile_stats != ("mean",):
            raise ValueError("only ridge on mean tactile features can be exported (std is not linear per window)")
        scalers = list(self.features.scalers)
        parts = []
        if self.modality in ("visual", "both"):
            s = scalers.pop(0)
            parts.append(g.standardized("visual", s.mean, s.std, 1.0 / np.sqrt(s.mean.size), clip=Z_CLIP))
        if scalers:  # the tactile groups: contiguous column blocks of the one tactile input, each its own weight
            z = g.standardized(
                "tactile",
                np.concatenate([s.mean for s in scalers]),
                np.concatenate([s.std for s in scalers]),
                1.0,
                clip=Z_CLIP,
            )
            weights = np.concatenate([np.full(s.mean.size, 1.0 / np.sqrt(s.mean.size)) for s in scalers])
            parts.append(g.op("Mul", z, g.const(weights)))
        z = g.concat(parts)
        return g.op("Add", g.op("MatMul", z, g.const(self.coef)), g.const(self.y_mean))

    def export(self, path, metadata: dict[str, str]):
        from models.offline.onnx_graph import export_graph

        return export_graph(self, path, metadata)


class KNNEstimator(Estimator):
    """k-nearest textures (distance-weighted); k chosen by leave-one-out over the training textures."""

    def __init__(self, modality: Modality, ks: tuple[int, ...] = (1, 3, 5, 7, 10)):
        self.modality = modality
        self.name = f"knn-{modality}"
        self.features = TextureFeatures(modality)
        self.ks = ks

    @staticmethod
    def _weighted(dist: np.ndarray, y: np.ndarray, k: int) -> np.ndarray:
        order = np.argsort(dist, axis=1)[:, :k]
        d = np.take_along_axis(dist, order, axis=1)
        w = 1.0 / (d + 1e-9)
        return np.einsum("nk,nkj->nj", w, y[order]) / w.sum(axis=1, keepdims=True)

    def fit(self, data: TextureData, seed: int) -> KNNEstimator:
        self.X = self.features.fit_transform(data)
        self.y = require_targets(data)
        dist = np.linalg.norm(self.X[:, None] - self.X[None], axis=2)
        np.fill_diagonal(dist, np.inf)
        losses = {
            k: float(np.mean(np.abs(self._weighted(dist, self.y, k) - self.y))) for k in self.ks if k < len(self.y)
        }
        self.k = min(losses, key=losses.get)
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        X = self.features.transform(data)
        dist = np.linalg.norm(X[:, None] - self.X[None], axis=2)
        return self._weighted(dist, self.y, self.k)

    def n_params(self) -> int:
        return int(self.X.size + self.y.size)

    def fit_info(self) -> dict:
        return {"k": self.k}


class SVREstimator(Estimator):
    """RBF support-vector regression per attribute on texture-level features.

    Chosen per attribute by inner 5-fold CV over the training textures (folds split textures,
    never views of one texture): C, and for modality "both" the tactile block's weight — 0 lets
    an attribute ignore touch where touch does not help it. views="all" trains on every
    augmented image view (prediction uses the original view, as the service sees one frame)."""

    def __init__(
        self,
        modality: Modality,
        Cs: tuple[float, ...] = (0.3, 1.0, 3.0, 10.0),
        views: str = "first",
        tactile_weights: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0),
    ):
        if views not in ("first", "all"):
            raise ValueError(f"views must be 'first' or 'all', got {views!r}")
        self.modality = modality
        self.name = f"svr-{modality}" + ("-views" if views == "all" else "")
        self.features = TextureFeatures(modality)
        self.Cs = Cs
        self.views = views
        self.tactile_weights = tactile_weights if modality == "both" else (1.0,)

    def _weighted(self, X: np.ndarray, w: float) -> np.ndarray:
        if self.modality != "both":
            return X
        n_visual = self.features.scalers[0].mean.size
        return np.concatenate([X[:, :n_visual], w * X[:, n_visual:]], axis=1)

    def fit(self, data: TextureData, seed: int) -> SVREstimator:
        from sklearn.model_selection import KFold
        from sklearn.svm import SVR

        if self.views == "all":
            X, row_tex = self.features.fit_transform_views(data)
        else:
            X, row_tex = self.features.fit_transform(data), np.arange(len(data))
        y = require_targets(data)
        self.y_mean, self.y_std = y.mean(axis=0), y.std(axis=0) + 1e-9
        ys = (y - self.y_mean) / self.y_std
        folds = [
            (np.isin(row_tex, tr), np.isin(row_tex, va))
            for tr, va in KFold(5, shuffle=True, random_state=seed).split(y)
        ]
        self.models, self.chosen = [], []
        for j in range(ys.shape[1]):
            target = ys[row_tex, j]
            scores = {}
            for w in self.tactile_weights:
                Xw = self._weighted(X, w)
                for C in self.Cs:
                    err = 0.0
                    for tr, va in folds:
                        m = SVR(C=C, epsilon=0.1, gamma="scale").fit(Xw[tr], target[tr])
                        err += float(np.sum(np.abs(m.predict(Xw[va]) - target[va])))
                    scores[(w, C)] = err
            w, C = min(scores, key=scores.get)
            self.chosen.append({"C": C, "tactile_weight": w} if self.modality == "both" else {"C": C})
            self.models.append(SVR(C=C, epsilon=0.1, gamma="scale").fit(self._weighted(X, w), target))
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        X = self.features.transform(data)
        out = [m.predict(self._weighted(X, c.get("tactile_weight", 1.0))) for m, c in zip(self.models, self.chosen)]
        return np.stack(out, axis=1) * self.y_std + self.y_mean

    def n_params(self) -> int:
        return int(sum(m.support_vectors_.size + m.dual_coef_.size for m in self.models))

    def fit_info(self) -> dict:
        return {"chosen": self.chosen}


class WindowSVREstimator(Estimator):
    """The paper's Tactile SVM: RBF SVR per attribute on individual MFCC windows (each labelled
    with its texture's mean rating); a texture's prediction averages its windows. At most
    `max_windows` windows per training texture keep the O(n²) kernel tractable."""

    name = "svr-tactile-windows"
    modality: Modality = "tactile"

    def __init__(self, C: float = 1.0, max_windows: int = 20):
        self.C = C
        self.max_windows = max_windows

    def fit(self, data: TextureData, seed: int) -> WindowSVREstimator:
        from sklearn.svm import SVR

        rng = np.random.default_rng(seed)
        rows, ys = [], []
        for w, y in zip(data.tactile, require_targets(data)):
            take = rng.permutation(len(w))[: self.max_windows]
            rows.append(w[take])
            ys.append(np.tile(y, (len(take), 1)))
        X, Y = np.concatenate(rows).astype(np.float64), np.concatenate(ys)
        self.scaler = Standardizer().fit(X)
        Xs = self.scaler.transform(X)
        self.y_mean, self.y_std = Y.mean(axis=0), Y.std(axis=0) + 1e-9
        Ys = (Y - self.y_mean) / self.y_std
        self.models = [SVR(C=self.C, epsilon=0.1, gamma="scale").fit(Xs, Ys[:, j]) for j in range(4)]
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        out = []
        for w in data.tactile:
            Xs = self.scaler.transform(w.astype(np.float64))
            out.append(np.stack([m.predict(Xs) for m in self.models], axis=1).mean(axis=0))
        return np.array(out) * self.y_std + self.y_mean

    def n_params(self) -> int:
        return int(sum(m.support_vectors_.size + m.dual_coef_.size for m in self.models))


class ShuffledLabels(Estimator):
    """Control: the wrapped estimator trained on training targets permuted across textures.
    If the evaluation leaks nothing, its error stays at predict-the-mean level."""

    def __init__(self, inner: Estimator):
        self.inner = inner
        self.name = f"shuffled-{inner.name}"
        self.modality = inner.modality

    def fit(self, data: TextureData, seed: int) -> ShuffledLabels:
        perm = np.random.default_rng(seed + 7919).permutation(len(data))
        self.inner.fit(data.with_targets(require_targets(data)[perm]), seed)
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        return self.inner.predict(data)

    def n_params(self) -> int:
        return self.inner.n_params()


class StackedEstimator(Estimator):
    """Per-attribute convex combination of base estimators, weights from out-of-fold predictions.

    Inside fit: K-fold over the training textures gives each base's out-of-fold predictions;
    non-negative least squares per attribute gives the weights (normalised to sum to 1); then
    every base is refit on all training textures. Lets touch carry the attributes where it
    helps (hard–soft) while vision carries the rest.

    bases: name → zero-argument factory of a fresh, unfitted estimator (the registry supplies
    them, so this module never imports the registry)."""

    def __init__(self, bases: dict[str, Callable[[], Estimator]], folds: int = 5):
        if not bases:
            raise ValueError("a stack needs at least one base estimator")
        self.bases = tuple(bases)
        self.factories = dict(bases)
        self.folds = folds
        self.name = "stack-" + "+".join(self.bases)
        self.modality = "both"

    def fit(self, data: TextureData, seed: int) -> StackedEstimator:
        from scipy.optimize import nnls
        from sklearn.model_selection import KFold

        y = require_targets(data)
        oof = np.zeros((len(self.bases), len(data), 4))
        for tr, va in KFold(self.folds, shuffle=True, random_state=seed).split(y):
            for b, name in enumerate(self.bases):
                oof[b, va] = self.factories[name]().fit(data.take(tr), seed).predict(data.take(va).with_targets(None))
        self.weights = np.zeros((4, len(self.bases)))
        for j in range(4):
            w, _ = nnls(oof[:, :, j].T, y[:, j])
            self.weights[j] = w / w.sum() if w.sum() > 0 else np.full(len(self.bases), 1 / len(self.bases))
        self.models = [self.factories[name]().fit(data, seed) for name in self.bases]
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        preds = np.stack([m.predict(data) for m in self.models])  # (bases, T, 4)
        return np.einsum("btj,jb->tj", preds, self.weights)

    def n_params(self) -> int:
        return int(sum(m.n_params() for m in self.models) + self.weights.size)

    def fit_info(self) -> dict:
        return {
            "weights": {a: dict(zip(self.bases, map(float, w))) for a, w in zip(("rs", "fb", "ss", "hs"), self.weights)}
        }
