"""HT-Net: input layout, pooling, depth variants, the faithful parameter count."""

from __future__ import annotations

import pytest
import torch

from models.offline.nets.htnet import HTNet, default_pool_after, temporal_max_pool2


def convlstm_params(c_in: int, filters: int, kernel: int) -> int:
    # input kernel + recurrent kernel + bias, for the four gates
    return 4 * filters * (kernel * c_in + kernel * filters + 1)


def test_faithful_parameter_count() -> None:
    net = HTNet()
    filters = (128, 256, 128, 128, 256, 128)
    channels = (1, *filters)
    expected = sum(convlstm_params(channels[n], channels[n + 1], 3) for n in range(6))
    expected += (13 * 128 + 6) * 128 + 128  # FC over flattened (13 rows × 128) ‖ 6 stats
    count = sum(p.numel() for p in net.parameters())
    print(f"\nfaithful HT-Net parameters: {count:,}")
    assert count == expected == 4_348_288
    assert count > 1e6


def test_faithful_forward_shape() -> None:
    net = HTNet()
    assert net.pool_after == (2, 4, 5)
    y = net(torch.randn(2, 526))
    assert y.shape == (2, 128)


def test_frames_are_time_coefficients_are_rows_stats_join_after() -> None:
    net = HTNet(filters=(4, 4), pool_after=(1,))
    seen = {}
    net.layers[0].register_forward_hook(lambda mod, args, out: None)  # forward() is bypassed; wrap the method
    original = net.layers[0].forward_channels_first

    def spy(x: torch.Tensor) -> torch.Tensor:
        seen["x"] = x
        return original(x)

    net.layers[0].forward_channels_first = spy  # type: ignore[method-assign]
    x = torch.randn(3, 526)
    net(x)
    # channel-first layout inside the stack: (B, time=40, channels=1, rows=13), frame-major
    assert torch.equal(seen["x"], x[:, :520].reshape(3, 40, 1, 13))
    assert net.fc.in_features == 13 * 4 + 6
    # the stats reach the output only through the final FC (not the recurrence)
    x2 = x.clone()
    x2[:, 520:] += 1.0
    with torch.no_grad():
        net.fc.weight[:, -6:] = 0.0
        torch.testing.assert_close(net(x), net(x2))


def test_default_pool_mapping() -> None:
    assert default_pool_after(6) == (2, 4, 5)
    assert default_pool_after(3) == (1, 2)
    assert default_pool_after(2) == (1,)
    assert default_pool_after(1) == ()
    assert default_pool_after(4) == (1, 3)


@pytest.mark.parametrize("filters", [(8,), (8, 8), (4, 8, 4)])
def test_depth_variants(filters: tuple[int, ...]) -> None:
    net = HTNet(filters=filters)
    assert len(net.layers) == len(filters)
    assert [layer.return_sequences for layer in net.layers] == [True] * (len(filters) - 1) + [False]
    assert net(torch.randn(2, 526)).shape == (2, 128)


def test_valid_padding_shrinks_rows() -> None:
    net = HTNet(filters=(4, 4, 4), padding="valid")
    assert net.fc.in_features == (13 - 3 * 2) * 4 + 6
    assert net(torch.randn(1, 526)).shape == (1, 128)


def test_other_layouts() -> None:
    net = HTNet(n_frames=10, n_coeffs=5, n_stats=0, filters=(3, 3), out_dim=7)
    assert net(torch.randn(2, 50)).shape == (2, 7)


def test_temporal_max_pool_known_answer() -> None:
    x = torch.tensor([1.0, 5.0, 3.0, 2.0, 9.0]).reshape(1, 5, 1, 1)
    assert temporal_max_pool2(x).flatten().tolist() == [5.0, 3.0]  # odd tail dropped (floor)


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="pool_after"):
        HTNet(filters=(4, 4), pool_after=(2,))
    with pytest.raises(ValueError, match="leave no step"):
        HTNet(n_frames=4, filters=(2, 2, 2, 2), pool_after=(1, 2, 3))
    with pytest.raises(ValueError, match="consume all"):
        HTNet(filters=(2,) * 7, padding="valid")
    with pytest.raises(ValueError, match=r"\(batch, 526\)"):
        HTNet(filters=(2,))(torch.randn(1, 520))
