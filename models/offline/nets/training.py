"""Training loop for the `models.offline.nets` networks: window ↔ image-view pairing, Adam, early stopping.

Data live as standardized arrays (`TrainArrays`): one row per tactile window, and per
texture V augmented views of its image's visual vector plus its 4 target ratings. Every
epoch pairs each window with a uniformly drawn view of its own texture (the paper pairs
tactile windows with augmented image views), so the visual branch sees every view over
training without storing N×V pairs.

Loss: RMSE over the batch's (window, rating) cells + ``recon_weight`` · MSE of HV-Net's
reconstruction of its visual input (when the model has an autoencoder). Early stopping
watches the validation RMSE only (the reconstruction is an auxiliary task), and the best
epoch's weights are restored.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

#: view used when a window needs one fixed partner (validation): view 0 of every texture
VALIDATION_VIEW = 0


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser and stopping settings (defaults: the paper's)."""

    lr: float = 1e-3
    batch: int = 128
    max_epochs: int = 200
    patience: int = 10
    recon_weight: float = 0.1
    weight_decay: float = 0.0
    seed: int = 0
    device: str = "cpu"
    num_threads: int | None = None
    #: windows drawn per texture each epoch (None: all). Windows of one texture are highly
    #: redundant; a fresh random subset each epoch keeps an epoch cheap without losing them.
    windows_per_texture: int | None = None
    #: image views per batch: a batch holds this many chunks of one texture's windows, each chunk
    #: paired with one random view, so the visual branch runs once per chunk, not once per window
    views_per_batch: int = 8

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.batch < 1 or self.max_epochs < 1 or self.patience < 1:
            raise ValueError(
                f"TrainConfig needs lr > 0, batch, max_epochs, patience ≥ 1; got lr={self.lr}, "
                f"batch={self.batch}, max_epochs={self.max_epochs}, patience={self.patience}"
            )
        if self.recon_weight < 0 or self.weight_decay < 0:
            raise ValueError(f"recon_weight and weight_decay must be ≥ 0, got {self.recon_weight}, {self.weight_decay}")
        if self.windows_per_texture is not None and self.windows_per_texture < 1:
            raise ValueError(f"windows_per_texture must be ≥ 1 or None, got {self.windows_per_texture}")
        if self.views_per_batch < 1:
            raise ValueError(f"views_per_batch must be ≥ 1, got {self.views_per_batch}")
        if self.num_threads is not None and self.num_threads < 1:
            raise ValueError(f"num_threads must be ≥ 1 or None, got {self.num_threads}")


@dataclass
class TrainArrays:
    """Standardized training (or validation) data.

    tactile: (N, F) float32 — one row per window.
    window_texture: (N,) int — index of each window's texture into the texture axis below.
    visual_views: (T, V, D) float32 — V augmented views of each texture's visual vector.
    targets: (T, 4) float32 — each texture's ratings.
    """

    tactile: np.ndarray
    window_texture: np.ndarray
    visual_views: np.ndarray
    targets: np.ndarray

    def __post_init__(self) -> None:
        t, wt, vv, y = self.tactile, self.window_texture, self.visual_views, self.targets
        if t.ndim != 2 or wt.shape != (t.shape[0],):
            raise ValueError(f"tactile must be (N, F) and window_texture (N,), got {t.shape} and {wt.shape}")
        if vv.ndim != 3 or vv.shape[1] < 1:
            raise ValueError(f"visual_views must be (T, V ≥ 1, D), got {vv.shape}")
        if y.ndim != 2 or y.shape[0] != vv.shape[0]:
            raise ValueError(f"targets must be (T, k) with T = {vv.shape[0]} textures, got {y.shape}")
        if not np.issubdtype(wt.dtype, np.integer) or (wt.size and (wt.min() < 0 or wt.max() >= vv.shape[0])):
            raise ValueError(f"window_texture must be integer indices into {vv.shape[0]} textures")
        if t.shape[0] == 0:
            raise ValueError("TrainArrays needs at least one window")

    @property
    def n_windows(self) -> int:
        return int(self.tactile.shape[0])


@dataclass
class TrainResult:
    """best_epoch: 0-based epoch whose weights the model holds; history: per-epoch losses
    ("train": mean batch loss incl. reconstruction, "val": validation RMSE, empty without val);
    val_loss: best validation RMSE (nan without val); seconds: wall time."""

    best_epoch: int
    history: dict[str, list[float]] = field(default_factory=lambda: {"train": [], "val": []})
    val_loss: float = math.nan
    seconds: float = 0.0


def rmse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Root of the mean squared error over every cell: pred, target (B, k) → scalar."""
    return torch.sqrt(torch.mean((pred - target) ** 2))


def _tensor(a: np.ndarray, device: str) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=device)


def predict_windows(
    model: nn.Module,
    tactile: np.ndarray,
    visual: np.ndarray,
    batch: int = 1024,
    visual_index: np.ndarray | None = None,
) -> np.ndarray:
    """Model outputs (standardized ratings) for paired windows, in eval mode without gradients.

    tactile: (N, F) float32; visual: (N, D) float32, one row per window, or — with
    visual_index (N,) — (U, D) rows shared by windows → (N, 4) float32.
    The model's train/eval mode is restored afterwards.
    """
    if visual_index is None:
        visual_index = np.arange(tactile.shape[0])
    if visual_index.shape != (tactile.shape[0],):
        raise ValueError(f"{tactile.shape[0]} tactile windows but {visual_index.shape[0]} visual indices")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    out = []
    try:
        with torch.no_grad():
            for start in range(0, tactile.shape[0], batch):
                rows, local = np.unique(visual_index[start : start + batch], return_inverse=True)
                t = _tensor(tactile[start : start + batch], str(device))
                v = _tensor(visual[rows], str(device))
                idx = torch.as_tensor(local, dtype=torch.long, device=device)
                out.append(model(t, v, idx)["ratings"].cpu().numpy())
    finally:
        model.train(was_training)
    return np.concatenate(out, axis=0) if out else np.zeros((0, 4), np.float32)


def _val_rmse(model: nn.Module, val: TrainArrays, batch: int) -> float:
    visual = val.visual_views[:, VALIDATION_VIEW]
    pred = predict_windows(model, val.tactile, visual, batch=max(batch, 1024), visual_index=val.window_texture)
    return float(np.sqrt(np.mean((pred - val.targets[val.window_texture]) ** 2)))


def _epoch_batches(
    by_texture: list[np.ndarray], chunk: int, per_batch: int, per_texture: int | None, rng: np.random.Generator
):
    """One epoch's batches: each texture's windows (a random `per_texture` of them, or all) cut
    into chunks of `chunk`, chunks shuffled, `per_batch` chunks per batch."""
    items = []
    for t, windows in enumerate(by_texture):
        picked = rng.permutation(windows)[:per_texture]
        items += [(t, picked[i : i + chunk]) for i in range(0, len(picked), chunk)]
    order = rng.permutation(len(items))
    for b in range(0, len(order), per_batch):
        yield [items[i] for i in order[b : b + per_batch]]


def train_net(
    model: nn.Module, data: TrainArrays, val: TrainArrays | None, cfg: TrainConfig, progress: bool = False
) -> TrainResult:
    """Train ``model`` in place on ``data``; early-stop on ``val`` and restore the best weights.

    Each epoch: shuffle the windows, pair each with a random view of its texture, Adam
    steps on RMSE(ratings) + recon_weight · MSE(reconstruction, visual). Without ``val``
    it trains ``max_epochs`` epochs and keeps the last weights. Deterministic given
    ``cfg.seed`` and the model's initial weights (torch seed for any torch randomness,
    a numpy Generator for shuffling and pairing).
    """
    start = time.perf_counter()
    previous_threads = torch.get_num_threads()
    if cfg.num_threads is not None:
        torch.set_num_threads(cfg.num_threads)
    try:
        return _train(model, data, val, cfg, progress, start)
    finally:
        torch.set_num_threads(previous_threads)


def _train(
    model: nn.Module, data: TrainArrays, val: TrainArrays | None, cfg: TrainConfig, progress: bool, start: float
) -> TrainResult:
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    model.to(cfg.device)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    tactile = _tensor(data.tactile, cfg.device)
    views = _tensor(data.visual_views, cfg.device)
    targets = _tensor(data.targets, cfg.device)
    n_views = data.visual_views.shape[1]

    result = TrainResult(best_epoch=-1)
    best_state: dict[str, torch.Tensor] | None = None
    best_val = math.inf
    stale = 0
    epochs = tqdm(range(cfg.max_epochs), desc="epochs", disable=not progress, leave=False)
    by_texture = [np.flatnonzero(data.window_texture == t) for t in range(data.visual_views.shape[0])]
    views_per_batch = min(cfg.views_per_batch, cfg.batch)
    chunk = max(1, cfg.batch // views_per_batch)
    for epoch in epochs:
        model.train()
        total, batches = 0.0, 0
        for members in _epoch_batches(by_texture, chunk, views_per_batch, cfg.windows_per_texture, rng):
            # members: list of (texture, window indices); each gets one random view of its texture
            idx = torch.as_tensor(np.concatenate([w for _, w in members]), device=cfg.device)
            tex = torch.as_tensor([t for t, _ in members], dtype=torch.long, device=cfg.device)
            view = torch.as_tensor(rng.integers(0, n_views, size=len(members)), device=cfg.device)
            owner = torch.as_tensor(np.repeat(np.arange(len(members)), [len(w) for _, w in members]), device=cfg.device)
            visual = views[tex, view]
            out = model(tactile[idx], visual, owner)
            loss = rmse(out["ratings"], targets[tex[owner]])
            if out.get("reconstruction") is not None and cfg.recon_weight > 0:
                loss = loss + cfg.recon_weight * torch.mean((out["reconstruction"] - visual) ** 2)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach())
            batches += 1
        result.history["train"].append(total / batches)

        if val is None:
            result.best_epoch = epoch
            continue
        val_loss = _val_rmse(model, val, cfg.batch)
        result.history["val"].append(val_loss)
        epochs.set_postfix(train=f"{total / batches:.4f}", val=f"{val_loss:.4f}")
        if val_loss < best_val:
            best_val, result.best_epoch, stale = val_loss, epoch, 0
            best_state = copy.deepcopy(model.state_dict())
        else:
            stale += 1
            if stale >= cfg.patience:
                break

    if best_state is not None:
        model.load_state_dict(best_state)
        result.val_loss = best_val
    model.eval()
    result.seconds = time.perf_counter() - start
    return result
