"""Baselines the paper compares against, rebuilt from its descriptions.

All share the `models.offline.nets` forward contract: forward(tactile, visual) →
{"ratings": (B, 4), "reconstruction": None}; the class attribute ``modality`` names
the inputs each one reads (the other argument is ignored).

- `ANN`: two fully connected branches (tactile, visual), each FC 128, 256, 256, 128 (ReLU);
  concat → FC 64 → FC 64 → FC 4.
- `Vision1DCNN`: a 1-D CNN over the visual vector (conv + max-pool stages → FC → 4).
- `HapticCNN`: a 2-D CNN "on image features". We only have the feature vector, not the
  image, so it is laid out as a near-square map (see `near_square_shape`) and the 2-D CNN
  runs on that map. The map has no spatial meaning (backbone channels ‖ GLCM cells), which
  is exactly what distinguishes this baseline from the 1-D one: 2-D kernels mix features
  that are ``cols`` apart in the vector as well as neighbours.
- `TactileCNNLSTM`: per-frame 1-D conv over the 13 MFCC coefficients, an LSTM over the
  40 frames, the 6 window stats joined to its last state, → FC → 4.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from models.offline.nets.fusion import N_RATINGS, MLPBranch, check_tactile_layout
from models.offline.nets.hvnet import KerasConv1d

Output = dict[str, torch.Tensor | None]


def gather_rows(x: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
    """x[index] when windows share rows of a de-duplicated visual batch (see VisuoTactileNet.forward)."""
    return x if index is None else x[index]


def _check_dims(name: str, **dims: int) -> None:
    bad = {k: v for k, v in dims.items() if v < 1}
    if bad:
        raise ValueError(f"{name} needs positive dimensions, got {bad}")


class ANN(nn.Module):
    """Two-branch MLP.

    forward(tactile: (B, tactile_dim), visual: (B, visual_dim)) → {"ratings": (B, 4), "reconstruction": None}.
    """

    modality = "both"

    def __init__(
        self,
        visual_dim: int,
        tactile_dim: int,
        branch: Sequence[int] = (128, 256, 256, 128),
        head: Sequence[int] = (64, 64),
    ) -> None:
        super().__init__()
        _check_dims("ANN", visual_dim=visual_dim, tactile_dim=tactile_dim)
        branch = tuple(branch)
        if not branch:
            raise ValueError("ANN branch needs at least one layer")
        self.tactile = MLPBranch(tactile_dim, branch[:-1], branch[-1])
        self.visual = MLPBranch(visual_dim, branch[:-1], branch[-1])
        self.head = MLPBranch(2 * branch[-1], tuple(head)[:-1], tuple(head)[-1])
        self.out = nn.Linear(tuple(head)[-1], N_RATINGS)

    def forward(self, tactile: torch.Tensor, visual: torch.Tensor, visual_index: torch.Tensor | None = None) -> Output:
        v = self.visual(visual)
        z = torch.cat([self.tactile(tactile), v if visual_index is None else v[visual_index]], dim=1)
        return {"ratings": self.out(self.head(z)), "reconstruction": None}


class _VisualCNN(nn.Module):
    """A CNN over the visual vector alone: conv stages (a subclass's ``_conv_stages``), flatten → FC ``fc``
    (ReLU) → FC 4. forward(tactile (ignored), visual: (B, visual_dim)) → {"ratings": (B, 4), "reconstruction": None}.
    """

    modality = "visual"

    def _head(self, flat: int, fc: int) -> None:
        self.fc = nn.Linear(flat, fc)
        self.out = nn.Linear(fc, N_RATINGS)

    def _conv_stages(self, visual: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, tactile: torch.Tensor, visual: torch.Tensor, visual_index: torch.Tensor | None = None) -> Output:
        z = self._conv_stages(visual)
        return {"ratings": gather_rows(self.out(F.relu(self.fc(z.flatten(1)))), visual_index), "reconstruction": None}


class Vision1DCNN(_VisualCNN):
    """1-D CNN over the visual vector as a 1-channel sequence: conv ('same', ReLU) + max-pool ``pool`` per stage."""

    def __init__(
        self,
        visual_dim: int,
        tactile_dim: int = 0,
        channels: Sequence[int] = (16, 32, 64),
        kernel: int = 5,
        pool: int = 4,
        fc: int = 64,
    ) -> None:
        super().__init__()
        _check_dims("Vision1DCNN", visual_dim=visual_dim, kernel=kernel, pool=pool, fc=fc)
        channels = tuple(channels)
        length = visual_dim // pool ** len(channels)
        if length < 1:
            raise ValueError(f"Vision1DCNN: visual_dim {visual_dim} too short for {len(channels)} pools of {pool}")
        chans = (1, *channels)
        self.convs = nn.ModuleList(KerasConv1d(chans[n], chans[n + 1], kernel) for n in range(len(channels)))
        self.pool = pool
        self._head(chans[-1] * length, fc)
        self.visual_dim = visual_dim

    def _conv_stages(self, visual: torch.Tensor) -> torch.Tensor:
        z = visual.unsqueeze(1)
        for conv in self.convs:
            z = F.max_pool1d(F.relu(conv(z)), self.pool)
        return z


def near_square_shape(n: int, max_aspect: float = 2.0) -> tuple[int, int]:
    """(rows, cols) for laying n values out as a map: rows·cols ≥ n, as square as possible.

    The largest divisor of n not above √n gives an exact fit (1536 → 32×48, 2304 → 48×48)
    when its aspect ratio is at most ``max_aspect``; otherwise (e.g. prime n) a
    ⌈√n⌉-wide map, zero-padded at the end.
    """
    if n < 1:
        raise ValueError(f"near_square_shape needs n ≥ 1, got {n}")
    rows = max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)
    if (n // rows) / rows <= max_aspect:
        return rows, n // rows
    cols = math.isqrt(n - 1) + 1
    return -(-n // cols), cols


class HapticCNN(_VisualCNN):
    """2-D CNN on the visual feature vector laid out as a near-square map (see module docstring):
    conv 3×3 ('same', ReLU) + max-pool 2 per stage."""

    def __init__(
        self,
        visual_dim: int,
        tactile_dim: int = 0,
        channels: Sequence[int] = (16, 32, 64),
        fc: int = 64,
    ) -> None:
        super().__init__()
        _check_dims("HapticCNN", visual_dim=visual_dim, fc=fc)
        channels = tuple(channels)
        self.map_shape = near_square_shape(visual_dim)
        rows, cols = self.map_shape
        if min(rows, cols) // 2 ** len(channels) < 1:
            raise ValueError(f"HapticCNN: a {rows}×{cols} map is too small for {len(channels)} pools of 2")
        chans = (1, *channels)
        self.convs = nn.ModuleList(nn.Conv2d(chans[n], chans[n + 1], 3, padding=1) for n in range(len(channels)))
        self._head(chans[-1] * (rows // 2 ** len(channels)) * (cols // 2 ** len(channels)), fc)
        self.visual_dim = visual_dim

    def _conv_stages(self, visual: torch.Tensor) -> torch.Tensor:
        rows, cols = self.map_shape
        pad = rows * cols - self.visual_dim
        z = F.pad(visual, (0, pad)) if pad else visual
        z = z.reshape(-1, 1, rows, cols)
        for conv in self.convs:
            z = F.max_pool2d(F.relu(conv(z)), 2)
        return z


class TactileCNNLSTM(nn.Module):
    """Per-frame CNN over the MFCC coefficients, then an LSTM over the frames.

    Each frame's 13 coefficients go through conv 3 ('same', ReLU) stages (time folded into
    batch, so every frame shares the weights), are flattened, and the LSTM reads the 40
    frame vectors; its last hidden state ‖ the window stats → FC ``fc`` (ReLU) → FC 4.
    forward(tactile: (B, n_frames·n_coeffs + n_stats), visual (ignored)) → {"ratings": (B, 4), "reconstruction": None}.
    """

    modality = "tactile"

    def __init__(
        self,
        visual_dim: int,
        tactile_dim: int,
        *,
        n_frames: int = 40,
        n_coeffs: int = 13,
        n_stats: int = 6,
        channels: Sequence[int] = (16, 32),
        hidden: int = 64,
        fc: int = 32,
    ) -> None:
        super().__init__()
        _check_dims("TactileCNNLSTM", n_frames=n_frames, n_coeffs=n_coeffs, hidden=hidden, fc=fc)
        check_tactile_layout(tactile_dim, n_frames, n_coeffs, n_stats)
        chans = (1, *tuple(channels))
        self.convs = nn.ModuleList(KerasConv1d(chans[n], chans[n + 1], 3) for n in range(len(chans) - 1))
        self.lstm = nn.LSTM(chans[-1] * n_coeffs, hidden, batch_first=True)
        self.fc = nn.Linear(hidden + n_stats, fc)
        self.out = nn.Linear(fc, N_RATINGS)
        self.n_frames, self.n_coeffs, self.n_stats = n_frames, n_coeffs, n_stats

    def forward(self, tactile: torch.Tensor, visual: torch.Tensor, visual_index: torch.Tensor | None = None) -> Output:
        n_mfcc = self.n_frames * self.n_coeffs
        z = tactile[:, :n_mfcc].reshape(-1, 1, self.n_coeffs)  # (B·T, 1, R): frames share the CNN
        for conv in self.convs:
            z = F.relu(conv(z))
        seq = z.flatten(1).unflatten(0, (-1, self.n_frames))  # (B, T, C·R)
        # explicit zero state sized from the graph input: left to nn.LSTM (or sized from
        # `seq`), the ONNX tracer freezes the example's batch size into the initial state
        zeros = seq.new_zeros((1, tactile.shape[0], self.lstm.hidden_size))
        _, (h, _) = self.lstm(seq, (zeros, zeros))
        z = torch.cat([h[-1], tactile[:, n_mfcc:]], dim=1)
        return {"ratings": self.out(F.relu(self.fc(z))), "reconstruction": None}
