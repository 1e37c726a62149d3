"""ConvLSTM1D with Keras semantics (``keras.layers.ConvLSTM1D``), in torch.

Input ``(batch, time, rows, channels)``. At every step the input convolution (kernel
``k`` over the rows axis, the layer's padding) and the recurrent convolution (same
kernel, always ``'same'``, no bias) each give ``4·filters`` channels, split in the Keras
gate order i, f, c (=g), o::

    i = σ(x*W_i + h*U_i + b_i)     f = σ(x*W_f + h*U_f + b_f)
    g = tanh(x*W_c + h*U_c + b_c)  o = σ(x*W_o + h*U_o + b_o)
    c' = f·c + i·g                 h' = o·tanh(c')

The forget-gate bias starts at 1 (Keras ``unit_forget_bias``), the input kernel is
Glorot-uniform and the recurrent kernel orthogonal, as Keras initialises them.

Efficiency: the input convolution does not depend on the state, so it runs once for
all time steps (time folded into batch); only the recurrent convolution is in the
Python loop. The first step skips it altogether (h₀ = c₀ = 0), which also keeps the
traced ONNX graph free of batch-sized zero tensors.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

Padding = Literal["same", "valid"]


def keras_same_padding(kernel: int) -> tuple[int, int]:
    """(left, right) zero padding that keeps the length for stride 1, as Keras/TF pads.

    TF puts the extra element of an even kernel on the right: k=4 → (1, 2).
    """
    total = kernel - 1
    return total // 2, total - total // 2


def conv1d_keras(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, padding: Padding) -> torch.Tensor:
    """1-D convolution (cross-correlation) with Keras padding.

    x: (N, C_in, L) float32; weight: (C_out, C_in, k) → (N, C_out, L) for 'same',
    (N, C_out, L − k + 1) for 'valid'. Odd kernels use the convolution's own symmetric
    padding; an even kernel pads its larger (right) amount on both sides and drops the
    surplus first output. Either way the ONNX graph is a Conv (+ one static Slice) rather
    than the dozen shape-computing nodes a traced ``F.pad`` becomes.
    """
    if padding == "valid":
        return F.conv1d(x, weight, bias)
    left, right = keras_same_padding(weight.shape[-1])
    out = F.conv1d(x, weight, bias, padding=right)
    return out[..., right - left :] if right != left else out


class ConvLSTM1D(nn.Module):
    """Keras-style 1-D convolutional LSTM.

    Args:
        in_channels: channels of the input, C.
        filters: hidden channels, F.
        kernel_size: kernel length over the rows axis, k.
        padding: 'same' or 'valid' for the input convolution (the recurrent one is
            always 'same', so the state keeps the input convolution's row count).
        return_sequences: return every step's hidden state, else only the last.

    Shapes (Keras layout): x: (B, T, R, C) → (B, T, R', F) if return_sequences else
    (B, R', F), with R' = R for 'same' and R − k + 1 for 'valid'.

    Parameters: ``weight_ih`` (4F, C, k) and ``bias`` (4F,) for the input convolution,
    ``weight_hh`` (4F, F, k) for the recurrent one; the 4F axis is blocks [i, f, c, o].
    """

    def __init__(
        self,
        in_channels: int,
        filters: int,
        kernel_size: int = 3,
        *,
        padding: Padding = "same",
        return_sequences: bool = False,
    ) -> None:
        super().__init__()
        if in_channels < 1 or filters < 1 or kernel_size < 1:
            raise ValueError(
                f"ConvLSTM1D needs in_channels, filters, kernel_size ≥ 1, got {in_channels}, {filters}, {kernel_size}"
            )
        if padding not in ("same", "valid"):
            raise ValueError(f"ConvLSTM1D padding must be 'same' or 'valid', got {padding!r}")
        self.in_channels = in_channels
        self.filters = filters
        self.kernel_size = kernel_size
        self.padding: Padding = padding
        self.return_sequences = return_sequences
        self.weight_ih = nn.Parameter(torch.empty(4 * filters, in_channels, kernel_size))
        self.weight_hh = nn.Parameter(torch.empty(4 * filters, filters, kernel_size))
        self.bias = nn.Parameter(torch.empty(4 * filters))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Keras defaults: Glorot-uniform kernel, orthogonal recurrent kernel, unit forget bias."""
        k, c, f = self.kernel_size, self.in_channels, self.filters
        # Keras kernel shape (k, C, 4F): fan_in = k·C, fan_out = k·4F
        bound = (6.0 / (k * c + k * 4 * f)) ** 0.5
        nn.init.uniform_(self.weight_ih, -bound, bound)
        # Keras' orthogonal initializer flattens (k, F, 4F) to a (k·F, 4F) matrix
        flat = torch.empty(k * f, 4 * f)
        nn.init.orthogonal_(flat)
        with torch.no_grad():
            self.weight_hh.copy_(flat.reshape(k, f, 4 * f).permute(2, 1, 0))
            self.bias.zero_()
            self.bias[f : 2 * f] = 1.0

    def out_rows(self, rows: int) -> int:
        """R' for an input with ``rows`` rows."""
        return rows if self.padding == "same" else rows - self.kernel_size + 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, T, R, C) float32 → (B, T, R', F) or (B, R', F)."""
        if x.dim() != 4 or x.shape[-1] != self.in_channels:
            raise ValueError(f"ConvLSTM1D expects (batch, time, rows, {self.in_channels}), got {tuple(x.shape)}")
        out = self.forward_channels_first(x.transpose(2, 3))
        return out.transpose(-1, -2)

    def forward_channels_first(self, x: torch.Tensor) -> torch.Tensor:
        """The same recurrence in torch's channel-first layout, for stacking without transposes.

        x: (B, T, C, R) → (B, T, F, R') if return_sequences else (B, F, R').
        """
        steps, rows = x.shape[1], x.shape[3]
        if steps < 1:
            raise ValueError("ConvLSTM1D needs at least one time step")
        if self.out_rows(rows) < 1:
            raise ValueError(f"ConvLSTM1D 'valid' kernel {self.kernel_size} is longer than {rows} rows")
        # input convolution for every step at once: (B·T, C, R) → (B, T, 4F, R')
        xz = conv1d_keras(x.flatten(0, 1), self.weight_ih, self.bias, self.padding).unflatten(0, (-1, steps))
        c = None
        h = None
        outputs = []
        for z in xz.unbind(1):
            if h is not None:
                z = z + conv1d_keras(h, self.weight_hh, None, "same")
            # split with a static size: exports as one Split node (chunk traces shape arithmetic)
            i, f, g, o = z.split(self.filters, dim=1)
            i, g, o = torch.sigmoid(i), torch.tanh(g), torch.sigmoid(o)
            c = i * g if c is None else torch.sigmoid(f) * c + i * g
            h = o * torch.tanh(c)
            if self.return_sequences:
                outputs.append(h)
        assert h is not None  # steps ≥ 1 was checked above
        return torch.stack(outputs, dim=1) if self.return_sequences else h

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.filters}, kernel_size={self.kernel_size}, "
            f"padding={self.padding!r}, return_sequences={self.return_sequences}"
        )
