"""Registry: every preset builds, has the shared contract, seeds reproduce, small ones are small."""

from __future__ import annotations

import pytest
import torch

from models.offline.nets import presets
from models.offline.nets.latency import param_count

REQUIRED = {
    "vtnet", "vtnet-compact", "vtnet-tiny", "vtnet-tactile", "vtnet-visual",
    "ann", "vision-1dcnn", "haptic-cnn", "tactile-cnn-lstm",
}  # fmt: skip
SMALL_NAMES = [n for n in presets.NAMES if n != "vtnet"]


def test_names() -> None:
    assert set(presets.NAMES) == REQUIRED


@pytest.mark.parametrize("name", SMALL_NAMES)
def test_contract(name: str) -> None:
    net = presets.build(name, 64, 526, seed=0)
    assert net.modality == presets.SPECS[name].modality
    out = net(torch.randn(3, 526), torch.randn(3, 64))
    assert set(out) == {"ratings", "reconstruction"}
    assert out["ratings"].shape == (3, 4)
    if out["reconstruction"] is not None:
        assert out["reconstruction"].shape == (3, 64)
        assert net.modality in ("both", "visual")


def test_seed_reproduces_weights_without_touching_global_rng() -> None:
    torch.manual_seed(123)
    before = torch.rand(1)
    torch.manual_seed(123)
    a = presets.build("vtnet-compact", 64, 526, seed=7)
    b = presets.build("vtnet-compact", 64, 526, seed=7)
    c = presets.build("vtnet-compact", 64, 526, seed=8)
    assert torch.rand(1) == before  # the global stream is where it was
    for (name, pa), pb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(pa, pb), name
    assert any(not torch.equal(pa, pc) for pa, pc in zip(a.parameters(), c.parameters(), strict=True))


def test_layout_presets_check_the_tactile_length() -> None:
    for name in presets.NAMES:
        if presets.SPECS[name].needs_layout:
            with pytest.raises(ValueError, match="does not match the MFCC layout"):
                presets.build(name, 64, 300)
        else:
            net = presets.build(name, 64, 300)
            assert net(torch.randn(2, 300), torch.randn(2, 64))["ratings"].shape == (2, 4)


def test_other_mfcc_layouts_pass_through() -> None:
    net = presets.build("vtnet-compact", 64, 20 * 13 + 6, n_frames=20)
    assert net(torch.randn(2, 266), torch.randn(2, 64))["ratings"].shape == (2, 4)


def test_small_presets_are_far_smaller_than_the_paper() -> None:
    paper = param_count(presets.build("vtnet", 1536, 526))
    print(f"\nvtnet parameters: {paper:,}")
    assert paper > 5e6
    for name in ("vtnet-compact", "vtnet-tiny", "vtnet-tactile", "vtnet-visual"):
        assert param_count(presets.build(name, 1536, 526)) < paper / 20, name


def test_unknown_name() -> None:
    with pytest.raises(ValueError, match="unknown network 'resnet'"):
        presets.build("resnet", 64, 526)
