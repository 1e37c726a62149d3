"""Kernel ridge and kernel SVR on texture-level features, with an additive kernel that keeps touch linear.

    k(x, x') = k_v(v, v') + w² · t·t'

v  the visual block: the texture's image views pooled (models.visual.pooling), standardised on the
   training textures (z bounded at ±Z_CLIP), ÷ √width;
t  the tactile block: the mean over the texture's windows of each window's standardised features
   (mean and std over the training windows, z bounded), ÷ √width;
k_v linear (v·v') or RBF exp(−γ‖v − v'‖²), γ relative to the median squared distance of the
   training textures.

The model is linear in t, and t is a mean over windows, so a texture-level fit serves window by
window: the exported graph answers each window (as the service asks it), and `predict` scores the
mean of those answers, each clipped to the rating range as the graph clips it — evaluation scores
what the service would say. The touch weight w, the kernel width and
the regularisation are chosen per attribute inside `fit` from the training textures only — this is
where each attribute weighs touch for itself (w = 0: the attribute ignores touch).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from models.inference.standardize import Z_CLIP, Standardizer
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimators import (
    Estimator,
    Modality,
    common_views,
    pooled_visual,
    require_targets,
    union_modality,
    window_mean,
)

VisualKernel = Literal["linear", "rbf"]
TACTILE_WEIGHTS = (0.0, 0.5, 1.0, 2.0)
RBF_GAMMAS = (0.25, 0.5, 1.0, 2.0, 4.0)  # × 1 / median squared distance
KRR_ALPHAS = tuple(np.logspace(-3, 2, 16).tolist())
SVR_CS = (1.0, 10.0)
SVR_EPSILON = 0.1  # in units of the attribute's standard deviation
SVR_FOLDS = 5


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) squared distances, by the same expansion the ONNX graph uses."""
    return np.maximum((a**2).sum(1)[:, None] - 2.0 * a @ b.T + (b**2).sum(1)[None, :], 0.0)


class PooledBlocks:
    """The visual and tactile blocks of the module docstring, fit on training textures.

    modality: which blocks; views: image views pooled per texture (None: every stored view);
    visual_blocks: None reads the whole visual vector as one block (÷ √width); names of visual feature groups
    (data.meta["visual_blocks"]: backbone, glcm, lbp, …) read only those columns, each group ÷ √(its width),
    so a 13-column colour group weighs as much as the 1280 backbone columns."""

    def __init__(self, modality: Modality, views: int | None = None, visual_blocks: tuple[str, ...] | None = None):
        if modality not in ("tactile", "visual", "both"):
            raise ValueError(f"modality must be tactile, visual or both, got {modality!r}")
        if views is not None and views < 1:
            raise ValueError(f"views must be ≥ 1, got {views}")
        if visual_blocks is not None and not visual_blocks:
            raise ValueError("visual_blocks must name at least one block (or be None: the whole vector)")
        self.modality = modality
        self.views = views
        self.visual_blocks = None if visual_blocks is None else tuple(visual_blocks)

    def _visual(self, data: TextureData) -> np.ndarray:
        pooled = pooled_visual(data, self.views)
        return pooled if self.visual_blocks is None else pooled[:, self.visual_columns]

    def _resolve_blocks(self, data: TextureData) -> None:
        layout = data.meta.get("visual_blocks")
        if layout is None:
            raise ValueError(f"visual blocks {list(self.visual_blocks)} asked for, but the data names no blocks")
        missing = [b for b in self.visual_blocks if b not in layout]
        if missing:
            raise ValueError(
                f"visual block(s) {missing} are not in the data (it has {list(layout)}): "
                "compute the features with those descriptors on (VisualConfig.descriptors)"
            )
        self.visual_columns = np.concatenate([np.arange(*layout[b]) for b in self.visual_blocks])
        self.visual_weights = np.concatenate(
            [
                np.full(layout[b][1] - layout[b][0], 1.0 / np.sqrt(layout[b][1] - layout[b][0]))
                for b in self.visual_blocks
            ]
        )

    @property
    def uses_visual(self) -> bool:
        return self.modality in ("visual", "both")

    @property
    def uses_tactile(self) -> bool:
        return self.modality in ("tactile", "both")

    def fit(self, data: TextureData) -> PooledBlocks:
        if self.uses_visual:
            if data.visual is None:
                raise ValueError("this estimator needs visual features, but the data has none")
            self.views = data.visual.shape[1] if self.views is None else self.views
            if self.visual_blocks is not None:
                self._resolve_blocks(data)
            self.visual_scaler = Standardizer().fit(self._visual(data))
        if self.uses_tactile:
            self.tactile_scaler = Standardizer().fit(np.concatenate(data.tactile).astype(np.float64))
        return self

    def transform_windows(self, data: TextureData) -> tuple[np.ndarray | None, list[np.ndarray] | None]:
        """(zv (T, Dv) | None, per texture its windows' zt (n_i, Dt) | None), each ÷ √width."""
        zv = zt = None
        if self.uses_visual:
            z = self.visual_scaler.transform(self._visual(data))
            zv = z / np.sqrt(z.shape[1]) if self.visual_blocks is None else z * self.visual_weights
        if self.uses_tactile:
            s = self.tactile_scaler
            zt = [s.transform(w.astype(np.float64)) / np.sqrt(s.mean.size) for w in data.tactile]
        return zv, zt

    def transform(self, data: TextureData) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Texture rows: (zv (T, Dv) | None, zt (T, Dt) | None) — zt the mean of the windows' rows."""
        zv, zt = self.transform_windows(data)
        return zv, None if zt is None else np.stack([w.mean(axis=0) for w in zt])

    def add_graph(self, g, visual: bool = True, tactile: bool = True) -> tuple[str | None, str | None]:
        """The same blocks per window in a GraphBuilder: (visual z, tactile z) output names; a block the
        model does not read (visual/tactile False) is left out, so the graph has no input for it."""
        zv = zt = None
        if self.uses_visual and visual and self.visual_blocks is not None:
            raise ValueError(
                f"a model on visual blocks {list(self.visual_blocks)} cannot be exported to ONNX yet "
                "(the graph reads the whole visual vector)"
            )
        if self.uses_visual and visual:
            s = self.visual_scaler
            zv = g.standardized("visual", s.mean, s.std, 1.0 / np.sqrt(s.mean.size), clip=Z_CLIP)
        if self.uses_tactile and tactile:
            s = self.tactile_scaler
            zt = g.standardized("tactile", s.mean, s.std, 1.0 / np.sqrt(s.mean.size), clip=Z_CLIP)
        return zv, zt


@dataclass
class Expansion:
    """One attribute's fitted function f(v, t) = Σ_i coef_i k_v(v, c_i) + t·beta_t + intercept (bipolar).

    gamma None: linear visual kernel, folded into beta_v = Σ_i coef_i c_i; centres unused then."""

    gamma: float | None
    tactile_weight: float
    centres: np.ndarray | None  # (m, Dv)
    coef: np.ndarray  # (m,)
    beta_v: np.ndarray | None  # (Dv,) for the linear kernel
    beta_t: np.ndarray | None  # (Dt,)
    intercept: float

    def __call__(self, zv: np.ndarray | None, zt: np.ndarray | None) -> np.ndarray:
        """Rows of zv (n, Dv) and zt (n, Dt) (either may be one row, broadcast) → (n,) bipolar."""
        out = np.asarray(self.intercept, float)
        if zv is not None:
            out = out + (
                zv @ self.beta_v if self.gamma is None else np.exp(-self.gamma * _sq_dist(zv, self.centres)) @ self.coef
            )
        if zt is not None and self.beta_t is not None:
            out = out + zt @ self.beta_t
        return np.atleast_1d(out)


def make_expansion(
    gamma: float | None, w: float, zv: np.ndarray | None, zt: np.ndarray | None, coef: np.ndarray, intercept: float
) -> Expansion:
    """An Expansion from dual coefficients over training rows (zv, zt)."""
    beta_v = zv.T @ coef if (zv is not None and gamma is None) else None
    beta_t = w**2 * (zt.T @ coef) if (zt is not None and w > 0) else None
    centres = zv if (zv is not None and gamma is not None) else None
    return Expansion(gamma, w, centres, coef, beta_v, beta_t, float(intercept))


class AdditiveKernelModel(Estimator):
    """Shared fit/predict/export of the additive-kernel models; subclasses fit one attribute's dual coefficients."""

    family = "kernel"

    def __init__(
        self,
        modality: Modality = "both",
        visual_kernel: VisualKernel = "rbf",
        views: int | None = None,
        tactile_weights: tuple[float, ...] = TACTILE_WEIGHTS,
        gammas: tuple[float, ...] = RBF_GAMMAS,
        visual_blocks: tuple[str, ...] | None = None,
    ):
        if visual_kernel not in ("linear", "rbf"):
            raise ValueError(f"visual_kernel must be linear or rbf, got {visual_kernel!r}")
        if not tactile_weights or min(tactile_weights) < 0:
            raise ValueError(f"tactile_weights must be non-negative, got {tactile_weights}")
        self.modality = modality
        self.visual_kernel = visual_kernel
        self.blocks = PooledBlocks(modality, views, visual_blocks)
        self.tactile_weights = tuple(tactile_weights) if modality == "both" else (1.0,)
        self.gammas = tuple(gammas) if (visual_kernel == "rbf" and modality != "tactile") else (None,)
        suffix = ("" if views is None else f"-v{views}") + (
            "" if visual_blocks is None else "-" + "+".join(visual_blocks)
        )
        self.name = f"{self.family}-{visual_kernel if modality != 'tactile' else 'linear'}-{modality}{suffix}"

    @property
    def views(self) -> int | None:
        return self.blocks.views if self.blocks.uses_visual else None

    def pooled_views(self, stored: int) -> int:
        return self.blocks.views or stored

    def _kernels(self, zv: np.ndarray | None, zt: np.ndarray | None) -> tuple[dict, np.ndarray | None, float]:
        """Visual kernel matrices per γ (absolute), the tactile Gram matrix, and the median squared distance."""
        kv, median = {}, 1.0
        if zv is None:
            kv[None] = np.zeros((len(zt), len(zt)))
        elif self.gammas == (None,):
            kv[None] = zv @ zv.T
        else:
            d2 = _sq_dist(zv, zv)
            off = d2[~np.eye(len(d2), dtype=bool)]
            median = float(np.median(off)) if off.size and np.median(off) > 0 else 1.0
            for rel in self.gammas:
                kv[rel / median] = np.exp(-(rel / median) * d2)
        kt = zt @ zt.T if zt is not None else None
        return kv, kt, median

    def fit(self, data: TextureData, seed: int) -> AdditiveKernelModel:
        y = require_targets(data)
        self.blocks.fit(data)
        zv, zt = self.blocks.transform(data)
        kv, kt, _ = self._kernels(zv, zt)
        self.expansions, self.chosen = [], []
        for gamma, w, coef, intercept, info in self._fit_attributes(kv, kt, y, seed):
            self.expansions.append(make_expansion(gamma, w, zv, zt, coef, intercept))
            self.chosen.append(info)
        # what the fitted model reads: an attribute that chose w = 0 ignores touch
        reads_touch = any(e.beta_t is not None for e in self.expansions)
        self.modality = union_modality(["visual"] * self.blocks.uses_visual + ["tactile"] * reads_touch)
        return self

    def _fit_attributes(self, kv: dict, kt: np.ndarray | None, y: np.ndarray, seed: int) -> list[tuple]:
        """Per attribute (column of y (n, 4)): (γ, touch weight, dual coefficients (n,), intercept, info)."""
        raise NotImplementedError

    def predict_windows(self, data: TextureData) -> list[np.ndarray]:
        """Per texture, (n_i, 4) bipolar answers of the exported graph to its windows, before the output clip."""
        zv, zt = self.blocks.transform_windows(data)
        out = []
        for i, windows in enumerate(data.tactile):
            v = None if zv is None else zv[i : i + 1]
            t = None if zt is None else zt[i]
            # an image-only texture has no windows: it gets one answer, from its image
            n = len(windows) if t is not None else max(len(windows), 1)
            rows = np.stack([np.broadcast_to(e(v, t), (n,)) for e in self.expansions], axis=1)
            out.append(rows)
        return out

    def predict(self, data: TextureData) -> np.ndarray:
        return window_mean(self.predict_windows(data))

    def n_params(self) -> int:
        """Numbers in the exported graph: the centres once (the attributes share them), per attribute its
        coefficients, linear weights and intercept."""
        centres = {id(e.centres): e.centres.size for e in self.expansions if e.centres is not None}
        total = sum(centres.values())
        for e in self.expansions:
            total += sum(0 if a is None else a.size for a in (e.beta_v, e.beta_t)) + e.coef.size + 1
        return int(total)

    def fit_info(self) -> dict:
        return {"chosen": self.chosen, "views": self.views}

    def add_graph(self, g) -> str:
        zv, zt = self.blocks.add_graph(
            g, visual=self.blocks.uses_visual, tactile=any(e.beta_t is not None for e in self.expansions)
        )
        cols, dist = [], {}
        for e in self.expansions:
            terms = [g.const(np.array([[e.intercept]]), "intercept")]
            if zv is not None and e.gamma is None:
                terms.append(g.op("MatMul", zv, g.const(e.beta_v[:, None], "beta_v")))
            elif zv is not None:
                key = id(e.centres)  # attributes that share centres share the distance computation
                if key not in dist:
                    dist[key] = g.squared_distances(zv, e.centres)
                k = g.op("Exp", g.op("Mul", dist[key], g.const(np.array(-e.gamma))))
                terms.append(g.op("MatMul", k, g.const(e.coef[:, None], "coef")))
            if zt is not None and e.beta_t is not None:
                terms.append(g.op("MatMul", zt, g.const(e.beta_t[:, None], "beta_t")))
            cols.append(terms[0] if len(terms) == 1 else g.op("Sum", *terms))
        return g.concat(cols)

    def export(self, path, metadata: dict[str, str]):
        from models.offline.onnx_graph import export_graph

        return export_graph(self, path, metadata)


def centred_loo_residuals(lam: np.ndarray, q: np.ndarray, y: np.ndarray, alphas: np.ndarray) -> np.ndarray:
    """The selection rule's leave-one-out residuals of kernel ridge with the mean rating as intercept,
    f = ȳ + k·(K + αI)⁻¹(y − ȳ): (y − Hy)_i / (1 − H_ii − 1/n) with H = K(K + αI)⁻¹, the 1/n for the intercept.

    lam, q   eigenvalues (n,) ≥ 0 and eigenvectors (n, n) of the kernel K over the n training textures
    y        (n, k) targets
    alphas   (a,) ridge strengths > 0
    returns  (a, n, k) residuals, one (n, k) per α (what α does not change is computed once)

    On centred columns (a linear kernel, K1 = 0) it is exact for ridge with a free intercept, the columns re-centred
    without texture i. An RBF kernel (or an uncentred touch block) is not centred, and there the leverage
    H_ii + 1/n overstates a weakly regularised fit's residuals — up to ruling out the smallest α where it reaches
    1 — so the criterion leans to stronger regularisation than `exact_loo_residuals`. It is the criterion the
    rule was fixed with (docs/models.md) and stays so; the exact one is the `selected-exact-loo` variant.
    """
    n = _loo_size(y, alphas)
    yc = y - y.mean(axis=0)
    qty, q2 = q.T @ yc, q**2
    out = np.empty((len(alphas), *y.shape))
    for i, alpha in enumerate(alphas):
        d = lam / (lam + alpha)
        hat = q2 @ d + 1.0 / n
        out[i] = (yc - q @ (d[:, None] * qty)) / np.maximum(1.0 - hat, 1e-9)[:, None]
    return out


def exact_loo_residuals(lam: np.ndarray, q: np.ndarray, y: np.ndarray, alphas: np.ndarray) -> np.ndarray:
    """Exact leave-one-out residuals of the same model, each texture's fit redone without it (mean and all), in
    closed form, for any kernel. Arguments and return as `centred_loo_residuals`.

    With G = (K + αI)⁻¹, kernel ridge without intercept leaves i out with residual (Gv)_i / G_ii for targets v;
    the intercept re-estimated without i, ȳ₋ᵢ, shifts the targets by a constant: (G(y − ȳ₋ᵢ))_i / G_ii.
    """
    n = _loo_size(y, alphas)
    yc = y - y.mean(axis=0)
    qty, q1, q2 = q.T @ yc, q.sum(axis=0), q**2
    shift = yc / (n - 1)  # ȳ − ȳ₋ᵢ = (y_i − ȳ) / (n − 1)
    out = np.empty((len(alphas), *y.shape))
    for i, alpha in enumerate(alphas):
        inv = 1.0 / (lam + alpha)
        g_y = q @ (inv[:, None] * qty)  # G(y − ȳ)
        g_1 = q @ (inv * q1)  # G1
        out[i] = (g_y + g_1[:, None] * shift) / (q2 @ inv)[:, None]
    return out


def _loo_size(y: np.ndarray, alphas: np.ndarray) -> int:
    if len(y) < 2:
        raise ValueError(f"leave-one-out needs at least 2 textures, got {len(y)}")
    if not np.all(np.asarray(alphas) > 0):
        raise ValueError(f"every alpha must be > 0, got {alphas}")
    return len(y)


LOO_RESIDUALS = {"centred": centred_loo_residuals, "exact": exact_loo_residuals}


class KernelRidgeEstimator(AdditiveKernelModel):
    """Kernel ridge regression per attribute. γ, the touch weight w and the ridge α are chosen per
    attribute by the closed-form leave-one-out MAE over the training textures (one eigendecomposition per kernel,
    no refits): `loo` "centred", the rule's criterion (`centred_loo_residuals`), or "exact"
    (`exact_loo_residuals`)."""

    family = "krr"

    def __init__(
        self,
        modality: Modality = "both",
        visual_kernel: VisualKernel = "rbf",
        views: int | None = None,
        alphas: tuple[float, ...] = KRR_ALPHAS,
        loo: Literal["centred", "exact"] = "centred",
        **kw,
    ):
        if loo not in LOO_RESIDUALS:
            raise ValueError(f"loo must be one of {', '.join(LOO_RESIDUALS)}, got {loo!r}")
        super().__init__(modality, visual_kernel, views, **kw)
        self.alphas = np.asarray(alphas, float)
        self.loo = loo
        if loo == "exact":
            self.name += "-exact-loo"

    def _fit_attributes(self, kv: dict, kt: np.ndarray | None, y: np.ndarray, seed: int) -> list[tuple]:
        n_out = y.shape[1]
        mean = y.mean(axis=0)
        yc = y - mean
        best: list[tuple] = [(np.inf,)] * n_out
        for gamma, kvm in kv.items():
            for w in self.tactile_weights:
                lam, q = np.linalg.eigh(kvm + (w**2 * kt if kt is not None else 0.0))
                lam = np.maximum(lam, 0.0)
                qty = q.T @ yc  # (n, 4)
                losses = np.mean(np.abs(LOO_RESIDUALS[self.loo](lam, q, y, self.alphas)), axis=1)  # (alphas, 4)
                for a, loss in zip(self.alphas, losses):
                    for j in range(n_out):
                        if loss[j] < best[j][0]:
                            best[j] = (float(loss[j]), gamma, w, float(a), lam, q, qty[:, j])
        out = []
        for j, (loss, gamma, w, a, lam, q, qty_j) in enumerate(best):
            coef = q @ (qty_j / (lam + a))
            out.append(
                (gamma, w, coef, float(mean[j]), {"gamma": gamma, "tactile_weight": w, "alpha": a, "loo_mae": loss})
            )
        return out


class KernelSVREstimator(AdditiveKernelModel):
    """ε-insensitive support-vector regression per attribute on the same kernel (robust to a few badly
    rated textures, as MAE is). C, γ and the touch weight per attribute by 5-fold CV over the training
    textures; targets standardised per attribute, ε = 0.1 standard deviations."""

    family = "ksvr"

    def __init__(
        self,
        modality: Modality = "both",
        visual_kernel: VisualKernel = "rbf",
        views: int | None = None,
        Cs: tuple[float, ...] = SVR_CS,
        gammas: tuple[float, ...] = (0.5, 1.0, 2.0),
        tactile_weights: tuple[float, ...] = (0.0, 1.0),
        **kw,
    ):
        super().__init__(modality, visual_kernel, views, tactile_weights=tactile_weights, gammas=gammas, **kw)
        self.Cs = tuple(Cs)

    def _fit_attributes(self, kv: dict, kt: np.ndarray | None, y: np.ndarray, seed: int) -> list[tuple]:
        import sklearn

        # hundreds of small fits: sklearn's per-call input validation would cost more than the fits
        with sklearn.config_context(assume_finite=True, skip_parameter_validation=True):
            return self._fit_svr(kv, kt, y, seed)

    def _fit_svr(self, kv: dict, kt: np.ndarray | None, y: np.ndarray, seed: int) -> list[tuple]:
        from sklearn.model_selection import KFold
        from sklearn.svm import SVR

        mean, std = y.mean(axis=0), y.std(axis=0) + 1e-9
        ys = (y - mean) / std
        if len(y) < 3:
            raise ValueError(f"kernel SVR needs at least 3 training textures for its inner folds, got {len(y)}")
        folds = list(KFold(min(SVR_FOLDS, len(y)), shuffle=True, random_state=seed).split(ys))
        best: list[tuple] = [(np.inf,)] * y.shape[1]
        for gamma, kvm in kv.items():
            for w in self.tactile_weights:
                k = kvm + (w**2 * kt if kt is not None else 0.0)
                for C in self.Cs:
                    err = np.zeros(y.shape[1])
                    for tr, va in folds:
                        k_tr, k_va = k[np.ix_(tr, tr)], k[np.ix_(va, tr)]
                        for j in range(y.shape[1]):
                            m = SVR(kernel="precomputed", C=C, epsilon=SVR_EPSILON).fit(k_tr, ys[tr, j])
                            pred = k_va[:, m.support_] @ m.dual_coef_[0] + m.intercept_[0]  # = m.predict, unvalidated
                            err[j] += float(np.abs(pred - ys[va, j]).sum())
                    for j in range(y.shape[1]):
                        if err[j] < best[j][0]:
                            best[j] = (err[j], gamma, w, C, k)
        out = []
        for j, (err, gamma, w, C, k) in enumerate(best):
            m = SVR(kernel="precomputed", C=C, epsilon=SVR_EPSILON).fit(k, ys[:, j])
            coef = np.zeros(len(y))
            coef[m.support_] = m.dual_coef_[0] * std[j]
            info = {
                "gamma": gamma,
                "tactile_weight": w,
                "C": C,
                "cv_mae": float(err / len(y) * std[j]),
                "support": int(m.support_.size),
            }
            out.append((gamma, w, coef, float(m.intercept_[0] * std[j] + mean[j]), info))
        return out


class MeanOfEstimator(Estimator):
    """The mean of several estimators' predictions (an ensemble of diverse members). Exports as one graph
    when every member has add_graph. members: name → zero-argument factory (from the registry)."""

    def __init__(self, members: dict, name: str = "mean-of"):
        if len(members) < 2:
            raise ValueError(f"a mean of estimators needs at least 2 members, got {len(members)}")
        self.factories = dict(members)
        self.name = name
        self.modality = union_modality(f().modality for f in self.factories.values())  # what it may read

    def fit(self, data: TextureData, seed: int) -> MeanOfEstimator:
        self.members = {k: f().fit(data, seed) for k, f in self.factories.items()}
        self.modality = union_modality(m.modality for m in self.members.values())
        return self

    def predict_windows(self, data: TextureData) -> list[np.ndarray]:
        per_member = [m.predict_windows(data) for m in self.members.values()]
        return [np.mean(rows, axis=0) for rows in zip(*per_member)]

    def predict(self, data: TextureData) -> np.ndarray:
        return window_mean(self.predict_windows(data))

    def n_params(self) -> int:
        return int(sum(m.n_params() for m in self.members.values()))

    def fit_info(self) -> dict:
        return {k: m.fit_info() for k, m in self.members.items()}

    @property
    def views(self) -> int | None:
        return common_views(self.members.values())

    def pooled_views(self, stored: int) -> int:
        return next(iter(self.factories.values()))().pooled_views(stored)

    def add_graph(self, g) -> str:
        return g.mean_of([m.add_graph(g) for m in self.members.values()])

    def export(self, path, metadata: dict[str, str]):
        from models.offline.onnx_graph import export_graph

        return export_graph(self, path, metadata)
