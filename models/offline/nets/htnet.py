"""HT-Net: the tactile branch, stacked ConvLSTM1D layers over the MFCC frames of a window.

How the 526 window features become the input sequence
------------------------------------------------------
The tactile window vector is ``[MFCC (40 frames × 13 coefficients, frame-major) | 6 stats]``
(speed min, max, mean, force min, max, mean). The first 520 values are reshaped to
``(time=40, rows=13, channels=1)``:

- **time = the 40 MFCC frames**: the frames are consecutive 25 ms slices of the 0.5 s
  stroke, so the LSTM recurrence runs along the physical time axis of the vibration;
- **rows = the 13 cepstral coefficients**: the convolution slides over the coefficient
  axis, where neighbouring coefficients describe neighbouring scales of the spectral
  envelope, so a small kernel shares weights across that axis;
- **channels = 1**: there is one MFCC value per (frame, coefficient).

The 6 speed/force statistics are *not* part of the sequence: they summarise the whole
window, not one frame, so repeating them over 40 steps (or appending them as fake rows)
would be meaningless to the recurrence. They are concatenated with the flattened final
hidden state of the last ConvLSTM layer, right before the fully connected layer.

Architecture (faithful config): six ConvLSTM1D layers with filters
(128, 256, 128, 128, 256, 128), kernel 3, 'same' padding, ``return_sequences`` between
layers; temporal max-pool 2 after layers 2, 4 and 5 (40 → 20 → 10 → 5 steps); the last
layer returns its final state (B, 13, 128) → flatten ‖ stats → FC → 128 (ReLU).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from models.offline.nets.convlstm import ConvLSTM1D, Padding

#: the paper's HT-Net
PAPER_FILTERS: tuple[int, ...] = (128, 256, 128, 128, 256, 128)
PAPER_POOL_AFTER: tuple[int, ...] = (2, 4, 5)


def default_pool_after(depth: int) -> tuple[int, ...]:
    """The paper's pooling positions (2, 4, 5 of 6) mapped onto a stack of ``depth`` layers.

    Each position p becomes round(p·depth/6), kept within 1..depth−1 (pooling after the
    last layer would pool a single state): 6 → (2, 4, 5), 3 → (1, 2), 2 → (1,), 1 → ().
    """
    if depth < 2:
        return ()
    return tuple(sorted({min(depth - 1, max(1, round(p * depth / 6))) for p in PAPER_POOL_AFTER}))


def temporal_max_pool2(x: torch.Tensor) -> torch.Tensor:
    """Max-pool 2 along time (floor, as Keras 'valid' pooling). x: (B, T, F, R) → (B, T//2, F, R)."""
    half = x.shape[1] // 2
    return torch.maximum(x[:, 0 : 2 * half : 2], x[:, 1 : 2 * half : 2])


class HTNet(nn.Module):
    """Tactile encoder: ConvLSTM1D stack over (frames, coefficients) + window stats → embedding.

    Args:
        n_frames, n_coeffs, n_stats: layout of the tactile vector (length n_frames·n_coeffs + n_stats).
        filters: filters per ConvLSTM layer; the tuple length is the depth.
        pool_after: 1-based layers followed by a temporal max-pool 2 (each < depth);
            None → the paper's (2, 4, 5) mapped onto the depth (`default_pool_after`).
        kernel: ConvLSTM kernel over the coefficient axis.
        padding: the ConvLSTM input convolution's padding ('same' keeps 13 rows).
        out_dim: embedding size.
        frame_pool: average adjacent MFCC frames by this factor before the stack (1: the paper).
            The compact presets use 4: the recurrence then runs 10 steps instead of 40, and on a
            CPU a ConvLSTM's cost is mostly per step, not per filter.

    forward(x: (B, n_frames·n_coeffs + n_stats) float32) → (B, out_dim).
    """

    def __init__(
        self,
        n_frames: int = 40,
        n_coeffs: int = 13,
        n_stats: int = 6,
        filters: Sequence[int] = PAPER_FILTERS,
        pool_after: Sequence[int] | None = None,
        kernel: int = 3,
        out_dim: int = 128,
        *,
        padding: Padding = "same",
        frame_pool: int = 1,
    ) -> None:
        super().__init__()
        filters = tuple(filters)
        if frame_pool < 1 or n_frames % frame_pool:
            raise ValueError(f"HTNet frame_pool must be ≥ 1 and divide n_frames={n_frames}, got {frame_pool}")
        if n_frames < 1 or n_coeffs < 1 or n_stats < 0:
            raise ValueError(
                f"HTNet needs n_frames, n_coeffs ≥ 1 and n_stats ≥ 0, got {n_frames}, {n_coeffs}, {n_stats}"
            )
        if not filters or any(f < 1 for f in filters):
            raise ValueError(f"HTNet filters must be a non-empty tuple of positive ints, got {filters}")
        if out_dim < 1:
            raise ValueError(f"HTNet out_dim must be ≥ 1, got {out_dim}")
        depth = len(filters)
        pools = default_pool_after(depth) if pool_after is None else tuple(sorted(set(pool_after)))
        if any(not 1 <= p < depth for p in pools):
            raise ValueError(f"HTNet pool_after {tuple(pool_after or ())} must name layers 1..{depth - 1} of {depth}")
        if n_frames // frame_pool // 2 ** len(pools) < 1:
            raise ValueError(f"HTNet: {len(pools)} temporal pools leave no step of {n_frames} frames")
        self.n_frames, self.n_coeffs, self.n_stats = n_frames, n_coeffs, n_stats
        self.in_dim = n_frames * n_coeffs + n_stats
        self.pool_after = pools
        self.frame_pool = frame_pool
        channels = (1, *filters)
        self.layers = nn.ModuleList(
            ConvLSTM1D(channels[n], channels[n + 1], kernel, padding=padding, return_sequences=n < depth - 1)
            for n in range(depth)
        )
        rows = n_coeffs
        for layer in self.layers:
            rows = layer.out_rows(rows)
        if rows < 1:
            raise ValueError(f"HTNet: {depth} 'valid' ConvLSTM layers of kernel {kernel} consume all {n_coeffs} rows")
        self.fc = nn.Linear(rows * filters[-1] + n_stats, out_dim)
        self.out_dim = out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, n_frames·n_coeffs + n_stats) float32 → embedding (B, out_dim)."""
        if x.dim() != 2 or x.shape[1] != self.in_dim:
            raise ValueError(f"HTNet expects (batch, {self.in_dim}), got {tuple(x.shape)}")
        n_mfcc = self.n_frames * self.n_coeffs
        # (B, 520) frame-major → (B, T=40, C=1, R=13): channel-first layout used inside the stack
        seq = x[:, :n_mfcc].reshape(-1, self.n_frames, 1, self.n_coeffs)
        if self.frame_pool > 1:
            seq = seq.reshape(-1, self.n_frames // self.frame_pool, self.frame_pool, 1, self.n_coeffs).mean(dim=2)
        for n, layer in enumerate(self.layers, start=1):
            seq = layer.forward_channels_first(seq)
            if n in self.pool_after:
                seq = temporal_max_pool2(seq)
        # seq is the last layer's final state (B, F, R); flatten in Keras order (rows, filters)
        state = seq.transpose(1, 2).flatten(1)
        return F.relu(self.fc(torch.cat([state, x[:, n_mfcc:]], dim=1)))
