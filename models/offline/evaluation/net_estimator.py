"""A torch network from models.offline.nets as a leave-one-texture-out estimator.

Inside fit: a validation split drawn from the training textures only (for
early stopping), standardisation fit on the remaining training textures, the
paper's window ↔ augmented-view pairing. A texture's prediction averages its
windows, each paired with the original image view.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.inference.standardize import Standardizer
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimators import Estimator, require_targets

MIN_VAL_TEXTURES = 2


def _stack_windows(data: TextureData) -> tuple[np.ndarray, np.ndarray]:
    """All windows (N, F) and their texture index (N,)."""
    X = np.concatenate(data.tactile).astype(np.float32)
    idx = np.concatenate([np.full(len(w), i) for i, w in enumerate(data.tactile)])
    return X, idx


class NetEstimator(Estimator):
    def __init__(
        self,
        name: str,
        *,
        val_fraction: float = 0.15,
        max_epochs: int = 200,
        patience: int = 10,
        lr: float = 1e-3,
        batch: int = 128,
        recon_weight: float = 0.1,
        weight_decay: float = 0.0,
        windows_per_texture: int | None = 16,
        views_per_batch: int = 8,
        val_windows_per_texture: int | None = 24,
        threads: int | None = None,
    ):
        from models.offline.nets.presets import SPECS

        if name not in SPECS:
            raise ValueError(f"unknown network {name!r}")
        if not 0 < val_fraction < 0.5:
            raise ValueError(f"val_fraction must lie in (0, 0.5), got {val_fraction}")
        self.name = name
        self.modality = SPECS[name].modality
        self.val_fraction = val_fraction
        self.val_windows_per_texture = val_windows_per_texture
        self.train_options = dict(
            max_epochs=max_epochs,
            patience=patience,
            lr=lr,
            batch=batch,
            recon_weight=recon_weight,
            weight_decay=weight_decay,
            windows_per_texture=windows_per_texture,
            views_per_batch=views_per_batch,
        )
        self.threads = threads or int(os.environ.get("OMP_NUM_THREADS", "0")) or None

    def _visual(self, data: TextureData) -> np.ndarray:
        # Tactile-only nets ignore the visual input; a 1-wide zero placeholder keeps one code path.
        if self.modality == "tactile" or data.visual is None:
            if self.modality != "tactile":
                raise ValueError(f"{self.name} needs visual features, but the data has none")
            return np.zeros((len(data), 1, 1), np.float32)
        return data.visual.astype(np.float32)

    def _arrays(self, data: TextureData, targets: np.ndarray | None):
        from models.offline.nets.training import TrainArrays

        X, idx = _stack_windows(data)
        views = self._visual(data)
        y = np.zeros((len(data), 4), np.float32) if targets is None else targets
        return TrainArrays(
            self.t_scaler.transform(X).astype(np.float32),
            idx,
            self.v_scaler.transform(views.reshape(-1, views.shape[2])).reshape(views.shape).astype(np.float32),
            ((y - self.y_scaler.mean) / self.y_scaler.std).astype(np.float32),
        )

    def fit(self, data: TextureData, seed: int) -> NetEstimator:
        from models.offline.nets.presets import build
        from models.offline.nets.training import TrainConfig, train_net

        y = require_targets(data).astype(np.float32)
        rng = np.random.default_rng(seed)
        n_val = max(MIN_VAL_TEXTURES, int(round(self.val_fraction * len(data))))
        perm = rng.permutation(len(data))
        val_idx, tr_idx = np.sort(perm[:n_val]), np.sort(perm[n_val:])
        train, val = data.take(tr_idx), data.take(val_idx)
        if self.val_windows_per_texture is not None:
            # A fixed random subset of each validation texture's windows: early stopping needs a
            # stable estimate, not every window, and validation runs every epoch.
            val = replace(
                val, tactile=[w[rng.permutation(len(w))[: self.val_windows_per_texture]] for w in val.tactile]
            )
        # Standardisation from the training part only (not even the validation textures).
        self.t_scaler = Standardizer().fit(_stack_windows(train)[0].astype(np.float64))
        views = self._visual(train)
        self.v_scaler = Standardizer().fit(views.reshape(-1, views.shape[2]).astype(np.float64))
        self.y_scaler = Standardizer().fit(y[tr_idx].astype(np.float64))
        layout_dim = data.tactile[0].shape[1]
        self.model = build(self.name, views.shape[2] if self.modality != "tactile" else 1, layout_dim, seed=seed)
        cfg = TrainConfig(seed=seed, num_threads=self.threads, **self.train_options)
        self.result = train_net(self.model, self._arrays(train, y[tr_idx]), self._arrays(val, y[val_idx]), cfg)
        return self

    def predict_windows(self, data: TextureData) -> list[np.ndarray]:
        """Per texture, (n_i, 4) bipolar predictions of its windows."""
        from models.offline.nets.training import predict_windows

        arr = self._arrays(data, None)
        pred = predict_windows(self.model, arr.tactile, arr.visual_views[:, 0], visual_index=arr.window_texture)
        pred = pred * self.y_scaler.std + self.y_scaler.mean
        return [pred[arr.window_texture == i] for i in range(len(data))]

    def predict(self, data: TextureData) -> np.ndarray:
        return np.stack([p.mean(axis=0) for p in self.predict_windows(data)])

    def n_params(self) -> int:
        from models.offline.nets.latency import param_count

        return param_count(self.model)

    def fit_info(self) -> dict:
        return {
            "best_epoch": self.result.best_epoch,
            "val_rmse_std_units": self.result.val_loss,
            "seconds": round(self.result.seconds, 2),
        }

    def raw(self):
        """The fitted net between raw-feature standardisation and bipolar output (see models.offline.nets.export)."""
        from models.offline.nets.export import raw_model

        return raw_model(
            self.model,
            tactile_mean=self.t_scaler.mean,
            tactile_std=self.t_scaler.std,
            visual_mean=self.v_scaler.mean,
            visual_std=self.v_scaler.std,
            target_mean=self.y_scaler.mean,
            target_std=self.y_scaler.std,
        )

    def widths(self) -> dict[str, int]:
        return {"tactile": self.t_scaler.mean.size, "visual": self.v_scaler.mean.size}

    def export(self, path: str | Path, metadata: dict[str, str]) -> Path:
        from models.offline.nets.export import export_raw

        return export_raw(self.raw(), self.modality, path, metadata, self.widths())


class NetEnsemble(Estimator):
    """The mean of `members` copies of a network trained with seeds seed, seed+1, …; each member
    draws its own validation split and initial weights inside the fold. Exports as one ONNX graph."""

    def __init__(self, name: str, members: int = 3, **options):
        if members < 2:
            raise ValueError(f"an ensemble needs at least 2 members, got {members}")
        self.members = [NetEstimator(name, **options) for _ in range(members)]
        self.name = f"{name}-ensemble"
        self.modality = self.members[0].modality

    def fit(self, data: TextureData, seed: int) -> NetEnsemble:
        for k, member in enumerate(self.members):
            member.fit(data, seed * len(self.members) + k)
        return self

    def predict(self, data: TextureData) -> np.ndarray:
        return np.mean([m.predict(data) for m in self.members], axis=0)

    def n_params(self) -> int:
        return sum(m.n_params() for m in self.members)

    def fit_info(self) -> dict:
        return {"members": [m.fit_info() for m in self.members]}

    def export(self, path: str | Path, metadata: dict[str, str]) -> Path:
        from models.offline.nets.export import export_raw, mean_of

        return export_raw(
            mean_of([m.raw() for m in self.members]), self.modality, path, metadata, self.members[0].widths()
        )
