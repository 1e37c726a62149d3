"""Training loop: pairing, loss definition, early stopping with restore, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from models.offline.nets import presets
from models.offline.nets.training import TrainArrays, TrainConfig, predict_windows, rmse, train_net


def toy_data(
    seed: int, n_textures: int = 6, windows_per: int = 12, views: int = 3, dim: int = 64, f: int = 526
) -> TrainArrays:
    """Targets are a linear function of a per-texture tactile signature plus noise: learnable."""
    rng = np.random.default_rng(seed)
    signature = rng.normal(size=(n_textures, f)).astype(np.float32)
    texture = np.repeat(np.arange(n_textures), windows_per)
    tactile = signature[texture] + 0.3 * rng.normal(size=(texture.size, f)).astype(np.float32)
    targets = (signature[:, :4] * 0.8).astype(np.float32)
    visual = rng.normal(size=(n_textures, 1, dim)) + 0.2 * rng.normal(size=(n_textures, views, dim))
    return TrainArrays(tactile, texture, visual.astype(np.float32), targets)


class Recorder(nn.Module):
    """Linear model that records the (tactile, visual) pairs it is trained on."""

    modality = "both"

    def __init__(self, f: int, d: int) -> None:
        super().__init__()
        self.lin = nn.Linear(f + d, 4)
        self.seen: list[tuple[torch.Tensor, torch.Tensor]] = []

    def forward(
        self, tactile: torch.Tensor, visual: torch.Tensor, visual_index: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor | None]:
        paired = visual if visual_index is None else visual[visual_index]
        if self.training:
            self.seen.append((tactile.detach().clone(), paired.detach().clone()))
        return {"ratings": self.lin(torch.cat([tactile, paired], dim=1)), "reconstruction": visual * 0.5}


def test_windows_are_paired_with_views_of_their_own_texture() -> None:
    n_tex, views = 4, 5
    texture = np.repeat(np.arange(n_tex), 6)
    tactile = texture[:, None].astype(np.float32)  # column 0 = texture id
    vv = np.zeros((n_tex, views, 2), np.float32)
    vv[:, :, 0] = np.arange(n_tex)[:, None]  # texture id
    vv[:, :, 1] = np.arange(views)[None, :]  # view id
    data = TrainArrays(tactile, texture, vv, np.zeros((n_tex, 4), np.float32))
    model = Recorder(1, 2)
    train_net(model, data, None, TrainConfig(max_epochs=8, batch=5))
    pairs = torch.cat([torch.cat(p, dim=1) for p in model.seen])  # (tactile id, visual texture, view)
    assert pairs.shape[0] == 8 * 24  # every window once per epoch
    assert torch.equal(pairs[:, 0], pairs[:, 1])
    assert set(pairs[:, 2].int().tolist()) == set(range(views))  # views are drawn, not fixed


def test_an_epoch_can_subsample_windows_and_shares_one_view_per_chunk() -> None:
    n_tex, views = 5, 4
    texture = np.repeat(np.arange(n_tex), 20)
    tactile = np.stack([texture, np.arange(texture.size)], axis=1).astype(np.float32)  # (texture id, window id)
    vv = np.zeros((n_tex, views, 2), np.float32)
    vv[:, :, 0] = np.arange(n_tex)[:, None]
    vv[:, :, 1] = np.arange(views)[None, :]
    model = Recorder(2, 2)
    train_net(
        model,
        TrainArrays(tactile, texture, vv, np.zeros((n_tex, 4), np.float32)),
        None,
        TrainConfig(max_epochs=3, batch=12, views_per_batch=3, windows_per_texture=8),
    )
    epoch_windows = sum(t.shape[0] for t, _ in model.seen) / 3
    assert epoch_windows == n_tex * 8  # 8 of each texture's 20 windows per epoch
    for t, v in model.seen:
        assert torch.equal(t[:, 0], v[:, 0])  # own texture
        assert len({(int(a), int(b)) for a, b in v.tolist()}) <= 3  # at most views_per_batch distinct views
    seen_windows = {int(w) for t, _ in model.seen for w in t[:, 1]}
    assert len(seen_windows) > n_tex * 8  # different subsets in different epochs


def test_loss_is_rmse_plus_weighted_reconstruction_mse() -> None:
    data = toy_data(0, views=1, dim=8, f=10)  # one view: the pairing is fixed
    torch.manual_seed(0)
    model = Recorder(10, 8)
    visual = torch.from_numpy(data.visual_views[data.window_texture, 0])
    with torch.no_grad():
        out = model(torch.from_numpy(data.tactile), visual)
    y = torch.from_numpy(data.targets[data.window_texture])
    expected = rmse(out["ratings"], y) + 0.1 * torch.mean((out["reconstruction"] - visual) ** 2)  # type: ignore[operator]
    result = train_net(model, data, None, TrainConfig(max_epochs=1, batch=10_000, lr=1e-12, recon_weight=0.1))
    assert result.history["train"][0] == pytest.approx(expected.item(), rel=1e-5)


def test_training_learns_and_is_deterministic() -> None:
    data, val = toy_data(0), toy_data(0)
    val.tactile = val.tactile + 0.1
    cfg = TrainConfig(max_epochs=15, batch=16, patience=50, seed=3)
    runs = []
    for _ in range(2):
        model = presets.build("vtnet-tiny", 64, 526, seed=1)
        runs.append((train_net(model, data, val, cfg), model))
    (r1, m1), (r2, m2) = runs
    assert r1.history == r2.history
    for (name, a), b in zip(m1.state_dict().items(), m2.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    assert r1.history["val"][-1] < 0.6 * r1.history["val"][0]
    other = train_net(
        presets.build("vtnet-tiny", 64, 526, seed=1), data, val, TrainConfig(max_epochs=3, batch=16, seed=4)
    )
    assert other.history["train"] != r1.history["train"][:3]


def test_early_stopping_restores_the_best_epoch() -> None:
    data = toy_data(1)
    val = toy_data(2)  # different signatures: validation gets worse while training fits
    model = presets.build("vtnet-tiny", 64, 526, seed=0)
    cfg = TrainConfig(max_epochs=60, batch=16, patience=3, lr=3e-3)
    result = train_net(model, data, val, cfg)
    vals = result.history["val"]
    assert result.best_epoch == int(np.argmin(vals))
    assert result.val_loss == min(vals)
    assert len(vals) == len(result.history["train"])
    assert len(vals) < 60 and len(vals) == result.best_epoch + 1 + cfg.patience
    # the weights are the best epoch's: re-evaluating gives its validation loss
    pred = predict_windows(model, val.tactile, val.visual_views[val.window_texture, 0])
    assert math.sqrt(np.mean((pred - val.targets[val.window_texture]) ** 2)) == pytest.approx(result.val_loss, rel=1e-5)


def test_without_validation_runs_all_epochs() -> None:
    result = train_net(presets.build("ann", 64, 526, seed=0), toy_data(0), None, TrainConfig(max_epochs=4, batch=32))
    assert len(result.history["train"]) == 4 and result.history["val"] == []
    assert result.best_epoch == 3 and math.isnan(result.val_loss)
    assert result.seconds > 0


def test_convlstm_model_trains() -> None:
    data = toy_data(0, n_textures=3, windows_per=4)
    result = train_net(presets.build("vtnet-compact", 64, 526, seed=0), data, None, TrainConfig(max_epochs=2, batch=6))
    assert all(np.isfinite(result.history["train"]))


def test_num_threads_is_restored() -> None:
    before = torch.get_num_threads()
    train_net(presets.build("ann", 64, 526, seed=0), toy_data(0), None, TrainConfig(max_epochs=1, num_threads=1))
    assert torch.get_num_threads() == before


def test_predict_windows_batches_and_restores_mode() -> None:
    model = presets.build("vtnet-tiny", 64, 526, seed=0)
    model.train()
    data = toy_data(0)
    visual = data.visual_views[data.window_texture, 1]
    a = predict_windows(model, data.tactile, visual, batch=7)
    b = predict_windows(model, data.tactile, visual)
    assert a.shape == (data.n_windows, 4)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert model.training


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="lr > 0"):
        TrainConfig(lr=0)
    with pytest.raises(ValueError, match="window_texture must be integer indices"):
        TrainArrays(
            np.zeros((2, 3), np.float32),
            np.array([0, 5]),
            np.zeros((2, 1, 4), np.float32),
            np.zeros((2, 4), np.float32),
        )
    with pytest.raises(ValueError, match="visual_views"):
        TrainArrays(
            np.zeros((2, 3), np.float32), np.array([0, 1]), np.zeros((2, 4), np.float32), np.zeros((2, 4), np.float32)
        )
