"""ConvLSTM1D: Keras semantics checked against hand computations and an explicit-loop reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.offline.nets.convlstm import ConvLSTM1D, conv1d_keras, keras_same_padding


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def reference_convlstm(x: np.ndarray, w_ih: np.ndarray, w_hh: np.ndarray, bias: np.ndarray, padding: str) -> np.ndarray:
    """Keras ConvLSTM1D with explicit loops. x: (B, T, R, C) → all hidden states (B, T, R', F).

    w_ih: (4F, C, k), w_hh: (4F, F, k), bias: (4F,), gate blocks [i, f, c, o].
    """
    b_, t_, r_, c_ = x.shape
    four_f, _, k = w_ih.shape
    f_ = four_f // 4
    left = (k - 1) // 2  # Keras puts the extra pad of an even kernel on the right
    r_out = r_ if padding == "same" else r_ - k + 1
    h = np.zeros((b_, r_out, f_))
    c = np.zeros((b_, r_out, f_))
    out = np.zeros((b_, t_, r_out, f_))
    for b in range(b_):
        for t in range(t_):
            z = np.zeros((r_out, four_f))
            for r in range(r_out):
                for g in range(four_f):
                    acc = bias[g]
                    for j in range(k):
                        # input conv: 'same' shifts the window left by `left`, 'valid' does not
                        src = r + j - (left if padding == "same" else 0)
                        if 0 <= src < r_:
                            for ch in range(c_):
                                acc += x[b, t, src, ch] * w_ih[g, ch, j]
                        # recurrent conv: always 'same'
                        src_h = r + j - left
                        if 0 <= src_h < r_out:
                            for ch in range(f_):
                                acc += h[b, src_h, ch] * w_hh[g, ch, j]
                    z[r, g] = acc
            i = 1 / (1 + np.exp(-z[:, 0:f_]))
            f = 1 / (1 + np.exp(-z[:, f_ : 2 * f_]))
            gg = np.tanh(z[:, 2 * f_ : 3 * f_])
            o = 1 / (1 + np.exp(-z[:, 3 * f_ :]))
            c[b] = f * c[b] + i * gg
            h[b] = o * np.tanh(c[b])
            out[b, t] = h[b]
    return out


def test_keras_same_padding_puts_the_extra_element_on_the_right() -> None:
    assert keras_same_padding(1) == (0, 0)
    assert keras_same_padding(3) == (1, 1)
    assert keras_same_padding(4) == (1, 2)
    assert keras_same_padding(5) == (2, 2)


@pytest.mark.parametrize("kernel", [1, 2, 3, 4, 5])
def test_conv1d_keras_same_matches_explicit_padding(kernel: int) -> None:
    torch.manual_seed(0)
    x = torch.randn(2, 3, 9)
    w = torch.randn(5, 3, kernel)
    b = torch.randn(5)
    left, right = keras_same_padding(kernel)
    expected = torch.nn.functional.conv1d(torch.nn.functional.pad(x, (left, right)), w, b)
    got = conv1d_keras(x, w, b, "same")
    assert got.shape == (2, 5, 9)
    torch.testing.assert_close(got, expected)
    assert conv1d_keras(x, w, b, "valid").shape == (2, 5, 9 - kernel + 1)


@pytest.mark.parametrize(
    ("padding", "kernel", "rows_out"), [("same", 3, 13), ("valid", 3, 11), ("same", 4, 13), ("valid", 5, 9)]
)
@pytest.mark.parametrize("return_sequences", [True, False])
def test_output_shapes(padding: str, kernel: int, rows_out: int, return_sequences: bool) -> None:
    layer = ConvLSTM1D(2, 6, kernel, padding=padding, return_sequences=return_sequences)  # type: ignore[arg-type]
    y = layer(torch.randn(3, 7, 13, 2))
    assert layer.out_rows(13) == rows_out
    assert y.shape == ((3, 7, rows_out, 6) if return_sequences else (3, rows_out, 6))


def test_single_step_known_answer() -> None:
    """k=1, one channel, one filter, one row: a single step worked out by hand."""
    layer = ConvLSTM1D(1, 1, 1)
    with torch.no_grad():
        layer.weight_ih.copy_(torch.tensor([0.5, -1.0, 2.0, 1.5]).reshape(4, 1, 1))  # i, f, c, o
        layer.weight_hh.fill_(7.0)  # irrelevant at the first step: h0 = 0
        layer.bias.copy_(torch.tensor([0.1, 1.0, -0.2, 0.0]))
    x = 0.8
    i = sigmoid(0.5 * x + 0.1)
    g = math.tanh(2.0 * x - 0.2)
    o = sigmoid(1.5 * x)
    c = i * g  # f · c0 = 0
    h = o * math.tanh(c)
    got = layer(torch.full((1, 1, 1, 1), x)).item()
    assert got == pytest.approx(h, abs=1e-6)
    # and by numbers, so the formula above cannot silently drift: i=σ(0.5)=0.62246, g=tanh(1.4)=0.88535,
    # c=0.55110, o=σ(1.2)=0.76852, h=o·tanh(c)=0.76852·0.50135
    assert h == pytest.approx(0.38529, abs=1e-5)


def test_two_steps_known_answer_uses_recurrent_weights_and_forget_gate() -> None:
    layer = ConvLSTM1D(1, 1, 1)
    with torch.no_grad():
        layer.weight_ih.copy_(torch.tensor([1.0, 1.0, 1.0, 1.0]).reshape(4, 1, 1))
        layer.weight_hh.copy_(torch.tensor([0.5, -0.5, 0.25, 2.0]).reshape(4, 1, 1))
        layer.bias.zero_()
    x0, x1 = 1.0, -0.5
    c1 = sigmoid(x0) * math.tanh(x0)
    h1 = sigmoid(x0) * math.tanh(c1)
    i2, f2 = sigmoid(x1 + 0.5 * h1), sigmoid(x1 - 0.5 * h1)
    g2, o2 = math.tanh(x1 + 0.25 * h1), sigmoid(x1 + 2.0 * h1)
    c2 = f2 * c1 + i2 * g2
    h2 = o2 * math.tanh(c2)
    got = layer(torch.tensor([x0, x1]).reshape(1, 2, 1, 1)).item()
    assert got == pytest.approx(h2, abs=1e-6)


@pytest.mark.parametrize(("padding", "kernel"), [("same", 3), ("valid", 3), ("same", 4)])
def test_matches_explicit_loop_reference(padding: str, kernel: int) -> None:
    torch.manual_seed(1)
    layer = ConvLSTM1D(2, 3, kernel, padding=padding, return_sequences=True)  # type: ignore[arg-type]
    with torch.no_grad():  # random (not init) values so every gate and bias matters
        for p in layer.parameters():
            p.copy_(torch.randn_like(p) * 0.5)
    x = torch.randn(2, 4, 6, 2)
    expected = reference_convlstm(
        x.numpy().astype(np.float64),
        layer.weight_ih.detach().numpy().astype(np.float64),
        layer.weight_hh.detach().numpy().astype(np.float64),
        layer.bias.detach().numpy().astype(np.float64),
        padding,
    )
    got = layer(x).detach().numpy()
    np.testing.assert_allclose(got, expected, atol=1e-5)
    layer.return_sequences = False
    np.testing.assert_allclose(layer(x).detach().numpy(), expected[:, -1], atol=1e-5)


def test_initialisation_follows_keras() -> None:
    torch.manual_seed(0)
    f, k = 5, 3
    layer = ConvLSTM1D(2, f, k)
    bias = layer.bias.detach()
    assert torch.equal(bias[f : 2 * f], torch.ones(f))  # unit_forget_bias
    assert torch.equal(bias[:f], torch.zeros(f)) and torch.equal(bias[2 * f :], torch.zeros(2 * f))
    # Keras' orthogonal init on the (k·F, 4F) flattening: k·F = 15 < 4F = 20 → orthonormal rows
    flat = layer.weight_hh.detach().permute(2, 1, 0).reshape(k * f, 4 * f)
    torch.testing.assert_close(flat @ flat.T, torch.eye(k * f), atol=1e-5, rtol=0)
    bound = math.sqrt(6.0 / (k * 2 + k * 4 * f))  # Glorot uniform on (k, C, 4F)
    assert layer.weight_ih.abs().max() <= bound


def test_gradients_reach_every_parameter_and_the_input() -> None:
    layer = ConvLSTM1D(2, 4, 3, return_sequences=True)
    x = torch.randn(2, 5, 7, 2, requires_grad=True)
    layer(x).pow(2).sum().backward()
    for name, p in layer.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_channels_first_path_equals_keras_layout() -> None:
    layer = ConvLSTM1D(3, 4, 3, return_sequences=True)
    x = torch.randn(2, 5, 8, 3)
    torch.testing.assert_close(layer(x), layer.forward_channels_first(x.transpose(2, 3)).transpose(-1, -2))


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="padding"):
        ConvLSTM1D(1, 4, 3, padding="causal")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="filters"):
        ConvLSTM1D(1, 0, 3)
    with pytest.raises(ValueError, match="rows"):
        ConvLSTM1D(1, 2, 5, padding="valid")(torch.randn(1, 2, 3, 1))
    with pytest.raises(ValueError, match=r"\(batch, time, rows, 2\)"):
        ConvLSTM1D(2, 2, 3)(torch.randn(1, 2, 3, 1))
