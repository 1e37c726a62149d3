"""HV-Net: the visual branch, a 1-D convolutional autoencoder over the visual feature vector.

The visual vector (backbone features ‖ GLCM, D = 1536 or 2304) is read as a 1-channel
sequence of length D. Encoder: conv ('same', ReLU) + max-pool 2, five times with filters
(256, 256, 128, 64, 32) and kernels (4, 4, 3, 3, 3). Decoder: the mirror image — upsample
to the length the matching encoder stage had, conv ('same') back to that stage's input
channels, ReLU except the last (linear, 1 channel) — so the reconstruction has exactly D
values even when D is not a multiple of 2⁵ (the upsampling is nearest-neighbour to the
recorded length: plain ×2 repetition when the length was even, one extra repeat when the
pooling had dropped an odd element). Embedding: bottleneck flattened → FC 512 → FC 128, ReLU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from models.offline.nets.convlstm import conv1d_keras


def scale_width(filters: int, width: float) -> int:
    """Filters after a width multiplier: rounded, never below 1."""
    return max(1, round(filters * width))


class KerasConv1d(nn.Conv1d):
    """nn.Conv1d with Keras padding ('same' pads the extra element of even kernels on the right).

    x: (B, C_in, L) → (B, C_out, L) for 'same', (B, C_out, L − k + 1) for 'valid'.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, padding: str = "same") -> None:
        super().__init__(in_channels, out_channels, kernel_size)
        if padding not in ("same", "valid"):
            raise ValueError(f"KerasConv1d padding must be 'same' or 'valid', got {padding!r}")
        self.keras_padding = padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return conv1d_keras(x, self.weight, self.bias, self.keras_padding)  # type: ignore[arg-type]


class HVNet(nn.Module):
    """Visual autoencoder + embedding head.

    Args:
        in_dim: D, length of the visual vector (≥ 2**len(widths), so the bottleneck is non-empty).
        widths: encoder filters per stage (before ``width`` scaling).
        kernels: encoder kernel per stage (the decoder uses them mirrored).
        fc: embedding head sizes; the last is the embedding size (128).
        width: multiplier on every conv's filters (compact variants).

    forward(x: (B, D) float32) → (embedding (B, fc[-1]), reconstruction (B, D)).
    """

    def __init__(
        self,
        in_dim: int,
        widths: Sequence[int] = (256, 256, 128, 64, 32),
        kernels: Sequence[int] = (4, 4, 3, 3, 3),
        fc: Sequence[int] = (512, 128),
        *,
        width: float = 1.0,
    ) -> None:
        super().__init__()
        widths, kernels, fc = tuple(widths), tuple(kernels), tuple(fc)
        if not widths or len(widths) != len(kernels):
            raise ValueError(f"HVNet needs one kernel per encoder stage, got widths {widths} and kernels {kernels}")
        if any(k < 1 for k in kernels) or any(w < 1 for w in widths) or width <= 0:
            raise ValueError(f"HVNet filters, kernels and width must be positive: {widths}, {kernels}, {width}")
        if not fc or any(n < 1 for n in fc):
            raise ValueError(f"HVNet fc sizes must be a non-empty tuple of positive ints, got {fc}")
        if in_dim < 2 ** len(widths):
            raise ValueError(
                f"HVNet in_dim {in_dim} is too short for {len(widths)} pooling stages (needs ≥ {2 ** len(widths)})"
            )
        self.in_dim = in_dim
        channels = (1, *(scale_width(w, width) for w in widths))
        # sequence length entering each encoder stage (max-pool 2 floors)
        self.stage_lengths: tuple[int, ...] = tuple(in_dim // 2**s for s in range(len(widths)))
        bottleneck_len = in_dim // 2 ** len(widths)

        self.encoder = nn.ModuleList(KerasConv1d(channels[s], channels[s + 1], kernels[s]) for s in range(len(widths)))
        # decoder stage j undoes encoder stage j (in reverse order): channels[j+1] → channels[j]
        self.decoder = nn.ModuleList(
            KerasConv1d(channels[s + 1], channels[s], kernels[s]) for s in reversed(range(len(widths)))
        )
        sizes = (channels[-1] * bottleneck_len, *fc)
        self.head = nn.ModuleList(nn.Linear(sizes[n], sizes[n + 1]) for n in range(len(fc)))
        self.out_dim = fc[-1]
        self.bottleneck_shape = (channels[-1], bottleneck_len)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, D) → bottleneck (B, C_last, D // 2**stages)."""
        z = x.unsqueeze(1)
        for conv in self.encoder:
            z = F.max_pool1d(F.relu(conv(z)), 2)
        return z

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """bottleneck (B, C_last, L_b) → reconstruction (B, D)."""
        for conv, length in zip(self.decoder, reversed(self.stage_lengths), strict=True):
            z = conv(F.interpolate(z, size=length, mode="nearest"))
            if conv is not self.decoder[-1]:
                z = F.relu(z)  # the last conv is linear: standardized inputs are signed
        return z.squeeze(1)

    def embed(self, z: torch.Tensor) -> torch.Tensor:
        """bottleneck (B, C_last, L_b) → embedding (B, fc[-1]), ReLU after every FC."""
        e = z.flatten(1)
        for layer in self.head:
            e = F.relu(layer(e))
        return e

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (B, D) float32 → (embedding (B, fc[-1]), reconstruction (B, D))."""
        if x.dim() != 2 or x.shape[1] != self.in_dim:
            raise ValueError(f"HVNet expects (batch, {self.in_dim}), got {tuple(x.shape)}")
        z = self.encode(x)
        return self.embed(z), self.decode(z)
