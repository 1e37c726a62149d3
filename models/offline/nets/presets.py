"""Named network presets: ``build(name, visual_dim, tactile_dim) -> nn.Module``.

| name               | modality | tactile layout | what |
|--------------------|----------|----------------|------|
| `vtnet`            | both     | MFCC 40×13+6   | the paper's sizes (HV-Net 256…32 filters, 6 ConvLSTMs 128/256) |
| `vtnet-compact`    | both     | MFCC           | HV-Net width ¼, 3 ConvLSTMs (16/32/16) on frames averaged by 4 |
| `vtnet-tiny`       | both     | any length     | MLP tactile branch, HV-Net width 1/16 with a small head |
| `vtnet-tactile`    | tactile  | MFCC           | the compact HT-Net alone |
| `vtnet-visual`     | visual   | any length     | the compact HV-Net alone |
| `ann`              | both     | any length     | baseline: two FC branches |
| `vision-1dcnn`     | visual   | any length     | baseline: 1-D CNN on the visual vector |
| `haptic-cnn`       | visual   | any length     | baseline: 2-D CNN on the visual vector as a map |
| `tactile-cnn-lstm` | tactile  | MFCC           | baseline: per-frame CNN + LSTM |

The faithful `vtnet` costs ~1.4 GMAC per window (1.16 G of it in the ConvLSTMs); the others
exist so that a window costs a small fraction of that.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from models.offline.nets.baselines import ANN, HapticCNN, TactileCNNLSTM, Vision1DCNN
from models.offline.nets.fusion import VisuoTactileNet, check_tactile_layout


@dataclass(frozen=True)
class Layout:
    """The MFCC window layout a tactile vector follows."""

    n_frames: int = 40
    n_coeffs: int = 13
    n_stats: int = 6


Builder = Callable[[int, int, Layout], nn.Module]

# three ConvLSTMs with the paper's pool-between-layers pattern over frames averaged by 4
# (10 → 5 → 2 steps); a ConvLSTM step costs mostly per-node overhead (in ONNX and in torch on a
# CPU alike), so the step count matters more than the filters
_COMPACT_TACTILE = {
    "tactile_filters": (16, 32, 16),
    "tactile_pool_after": (1, 2),
    "tactile_out": 64,
    "tactile_frame_pool": 4,
}
_COMPACT_VISUAL = {"width": 0.25, "visual_fc": (128, 64)}


def _layout_kwargs(layout: Layout) -> dict[str, int]:
    return {"n_frames": layout.n_frames, "n_coeffs": layout.n_coeffs, "n_stats": layout.n_stats}


@dataclass(frozen=True)
class Spec:
    """A preset: its builder, the modality it reads, and whether it needs the MFCC layout."""

    builder: Builder
    modality: str
    needs_layout: bool
    description: str


SPECS: dict[str, Spec] = {
    "vtnet": Spec(
        lambda v, t, lay: VisuoTactileNet(v, t, **_layout_kwargs(lay)),
        "both",
        True,
        "Visuo-tactile Net at the paper's sizes",
    ),
    "vtnet-compact": Spec(
        lambda v, t, lay: VisuoTactileNet(v, t, **_COMPACT_VISUAL, **_COMPACT_TACTILE, **_layout_kwargs(lay)),
        "both",
        True,
        "Visuo-tactile Net, HV-Net width 1/4, ConvLSTM layers of 16/32/16 filters over frames averaged by 4",
    ),
    "vtnet-tiny": Spec(
        lambda v, t, lay: VisuoTactileNet(
            v,
            t,
            width=1 / 16,
            visual_fc=(64, 32),
            tactile_branch="mlp",
            tactile_hidden=(64,),
            tactile_out=32,
            head=(32, 32, 16),
        ),
        "both",
        False,
        "Visuo-tactile Net with an MLP tactile branch and a 1/16-width HV-Net",
    ),
    "vtnet-tactile": Spec(
        lambda v, t, lay: VisuoTactileNet(v, t, modality="tactile", **_COMPACT_TACTILE, **_layout_kwargs(lay)),
        "tactile",
        True,
        "compact HT-Net alone",
    ),
    "vtnet-visual": Spec(
        lambda v, t, lay: VisuoTactileNet(v, t, modality="visual", **_COMPACT_VISUAL),
        "visual",
        False,
        "compact HV-Net alone",
    ),
    "ann": Spec(lambda v, t, lay: ANN(v, t), "both", False, "baseline: two-branch MLP"),
    "vision-1dcnn": Spec(lambda v, t, lay: Vision1DCNN(v, t), "visual", False, "baseline: 1-D CNN on visual features"),
    "haptic-cnn": Spec(lambda v, t, lay: HapticCNN(v, t), "visual", False, "baseline: 2-D CNN on visual features"),
    "tactile-cnn-lstm": Spec(
        lambda v, t, lay: TactileCNNLSTM(v, t, **_layout_kwargs(lay)),
        "tactile",
        True,
        "baseline: per-frame CNN + LSTM on MFCC frames",
    ),
}

NAMES: tuple[str, ...] = tuple(SPECS)


def build(
    name: str,
    visual_dim: int,
    tactile_dim: int,
    *,
    n_frames: int = 40,
    n_coeffs: int = 13,
    n_stats: int = 6,
    seed: int | None = None,
) -> nn.Module:
    """Build preset ``name`` for visual vectors of ``visual_dim`` and tactile vectors of ``tactile_dim``.

    Presets that need the MFCC layout check tactile_dim = n_frames·n_coeffs + n_stats.
    ``seed`` makes the initial weights reproducible without touching the global RNG.
    The returned module has a ``modality`` attribute and the `models.offline.nets` forward contract.
    """
    if name not in SPECS:
        raise ValueError(f"unknown network {name!r}; known: {', '.join(NAMES)}")
    spec = SPECS[name]
    layout = Layout(n_frames, n_coeffs, n_stats)
    if spec.needs_layout:
        check_tactile_layout(tactile_dim, n_frames, n_coeffs, n_stats)
    if seed is None:
        return spec.builder(visual_dim, tactile_dim, layout)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return spec.builder(visual_dim, tactile_dim, layout)
