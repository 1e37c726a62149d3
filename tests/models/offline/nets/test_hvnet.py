"""HV-Net: shapes for any D, mirrored decoder, width scaling, parameter count."""

from __future__ import annotations

import pytest
import torch

from models.offline.nets.hvnet import HVNet, KerasConv1d, scale_width


@pytest.mark.parametrize("dim", [1536, 2304, 1000, 37])
def test_embedding_and_reconstruction_shapes(dim: int) -> None:
    net = HVNet(dim, width=0.25)
    embedding, reconstruction = net(torch.randn(2, dim))
    assert embedding.shape == (2, 128)
    assert reconstruction.shape == (2, dim)
    assert (embedding >= 0).all()  # ReLU embedding


def test_encoder_and_decoder_mirror_each_other() -> None:
    net = HVNet(1536)
    enc = [(c.in_channels, c.out_channels, c.kernel_size[0]) for c in net.encoder]
    dec = [(c.in_channels, c.out_channels, c.kernel_size[0]) for c in net.decoder]
    assert enc == [(1, 256, 4), (256, 256, 4), (256, 128, 3), (128, 64, 3), (64, 32, 3)]
    assert dec == [(32, 64, 3), (64, 128, 3), (128, 256, 3), (256, 256, 4), (256, 1, 4)]
    assert net.bottleneck_shape == (32, 48)  # 1536 / 2**5
    assert net.stage_lengths == (1536, 768, 384, 192, 96)
    assert net.head[0].in_features == 32 * 48 and net.head[0].out_features == 512


def test_odd_lengths_reconstruct_every_position() -> None:
    """D = 37: the pools floor 37 → 18 → 9 → 4 → 2 → 1; the decoder returns to exactly 37."""
    net = HVNet(37, widths=(4, 4, 4, 4, 4))
    assert net.stage_lengths == (37, 18, 9, 4, 2)
    x = torch.randn(3, 37, requires_grad=True)
    _, rec = net(x)
    assert rec.shape == (3, 37)
    rec[:, -1].sum().backward()  # the last (odd) position is connected to the input
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_width_scales_filters_only() -> None:
    net = HVNet(1536, width=0.25)
    assert [c.out_channels for c in net.encoder] == [64, 64, 32, 16, 8]
    assert scale_width(3, 0.1) == 1  # never zero filters


def test_faithful_parameter_count() -> None:
    def conv(cin: int, cout: int, k: int) -> int:
        return cin * cout * k + cout

    encoder = conv(1, 256, 4) + conv(256, 256, 4) + conv(256, 128, 3) + conv(128, 64, 3) + conv(64, 32, 3)
    decoder = conv(32, 64, 3) + conv(64, 128, 3) + conv(128, 256, 3) + conv(256, 256, 4) + conv(256, 1, 4)
    head = (32 * 48 * 512 + 512) + (512 * 128 + 128)
    assert sum(p.numel() for p in HVNet(1536).parameters()) == encoder + decoder + head == 1_638_433


def test_keras_conv_same_keeps_length_for_even_kernels() -> None:
    conv = KerasConv1d(1, 2, 4)
    assert conv(torch.randn(1, 1, 10)).shape == (1, 2, 10)


def test_can_learn_to_reconstruct() -> None:
    torch.manual_seed(0)
    net = HVNet(64, widths=(8, 8), kernels=(3, 3), fc=(16, 8))
    x = torch.randn(16, 64).cumsum(1) / 8  # smooth signals an autoencoder can compress
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = None
    for _ in range(60):
        loss = torch.mean((net(x)[1] - x) ** 2)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.3 * first


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="too short"):
        HVNet(16)
    with pytest.raises(ValueError, match="one kernel per encoder stage"):
        HVNet(64, widths=(4, 4), kernels=(3,))
    with pytest.raises(ValueError, match=r"\(batch, 64\)"):
        HVNet(64, widths=(4,), kernels=(3,))(torch.randn(2, 65))
