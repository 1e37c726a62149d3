"""Baselines: layer sizes from the paper, shapes, modality, the near-square map."""

from __future__ import annotations

import pytest
import torch

from models.offline.nets.baselines import ANN, HapticCNN, TactileCNNLSTM, Vision1DCNN, near_square_shape


def test_ann_layer_sizes() -> None:
    net = ANN(1536, 526)
    assert [(layer.in_features, layer.out_features) for layer in net.tactile.layers] == [
        (526, 128),
        (128, 256),
        (256, 256),
        (256, 128),
    ]
    assert [(layer.in_features, layer.out_features) for layer in net.visual.layers] == [
        (1536, 128),
        (128, 256),
        (256, 256),
        (256, 128),
    ]
    assert [(layer.in_features, layer.out_features) for layer in net.head.layers] == [(256, 64), (64, 64)]
    assert (net.out.in_features, net.out.out_features) == (64, 4)


@pytest.mark.parametrize(
    ("cls", "modality"), [(ANN, "both"), (Vision1DCNN, "visual"), (HapticCNN, "visual"), (TactileCNNLSTM, "tactile")]
)
@pytest.mark.parametrize("visual_dim", [1536, 2304])
def test_shapes_and_modality(cls: type, modality: str, visual_dim: int) -> None:
    net = cls(visual_dim, 526)
    assert cls.modality == modality == net.modality
    out = net(torch.randn(3, 526), torch.randn(3, visual_dim))
    assert out["ratings"].shape == (3, 4)
    assert out["reconstruction"] is None


def test_visual_baselines_ignore_tactile_and_tactile_ignores_visual() -> None:
    t, v = torch.randn(2, 526), torch.randn(2, 64)
    for net in (Vision1DCNN(64), HapticCNN(64)):
        torch.testing.assert_close(net(t, v)["ratings"], net(torch.randn(2, 526), v)["ratings"])
    lstm = TactileCNNLSTM(64, 526)
    torch.testing.assert_close(lstm(t, v)["ratings"], lstm(t, torch.randn(2, 64))["ratings"])


def test_near_square_shape() -> None:
    assert near_square_shape(1536) == (32, 48)
    assert near_square_shape(2304) == (48, 48)
    assert near_square_shape(1537) == (29, 53)  # 1537 = 29·53 and 53/29 ≤ 2: exact fit
    assert near_square_shape(2062) == (45, 46)  # 2062 = 2·1031 is too elongated: padded map
    assert near_square_shape(7) == (3, 3)  # prime: padded map
    for n in (5, 100, 1000, 1537, 2039):
        rows, cols = near_square_shape(n)
        assert rows * cols >= n and rows * cols - n < cols


def test_haptic_cnn_pads_when_the_map_is_not_exact() -> None:
    net = HapticCNN(2039)  # prime
    assert net(torch.randn(2, 526), torch.randn(2, 2039))["ratings"].shape == (2, 4)


def test_tactile_cnn_lstm_shares_the_frame_cnn_and_reads_stats() -> None:
    net = TactileCNNLSTM(64, 526)
    assert net.lstm.input_size == 32 * 13
    t = torch.randn(2, 526)
    t2 = t.clone()
    t2[:, 520:] += 1.0
    assert not torch.allclose(net(t, None)["ratings"], net(t2, None)["ratings"])  # type: ignore[arg-type]


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="does not match"):
        TactileCNNLSTM(64, 520)
    with pytest.raises(ValueError, match="too short"):
        Vision1DCNN(32)
    with pytest.raises(ValueError, match="too small"):
        HapticCNN(16)
