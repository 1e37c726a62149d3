"""ResNet-50 (v1.5, as torchvision builds it) with torchvision's parameter names.

Written here so the project needs no torchvision, yet a checkpoint saved by
torchvision (`resnet50-*.pth` in torch's hub cache) loads with strict=True.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

RESNET50_DIM = 2048
RESNET50_LAYERS = (3, 4, 6, 3)
# torchvision's resnet50 state_dict: 161 parameters + 53 BatchNorms × 3 buffers.
RESNET50_STATE_DICT_LEN = 320
# The normalisation torchvision's ImageNet ResNet-50 weights were trained with,
# per RGB channel, on [0, 1] intensities.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class Bottleneck(nn.Module):
    """1×1 reduce → 3×3 (carries the stride, as in torchvision's v1.5) → 1×1 expand ×4, plus shortcut."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None) -> None:
        super().__init__()
        width = planes
        self.conv1 = nn.Conv2d(inplanes, width, kernel_size=1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, kernel_size=3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, planes * self.expansion, kernel_size=1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


class ResNet50(nn.Module):
    """ResNet-50 for 3-channel ImageNet-normalised input (n, 3, H, W).

    forward   → (n, num_classes) logits
    features  → (n, 2048) global-average-pooled final feature map
    """

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self.inplanes = 64
        self.conv1 = nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(64, RESNET50_LAYERS[0])
        self.layer2 = self._make_layer(128, RESNET50_LAYERS[1], stride=2)
        self.layer3 = self._make_layer(256, RESNET50_LAYERS[2], stride=2)
        self.layer4 = self._make_layer(512, RESNET50_LAYERS[3], stride=2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(512 * Bottleneck.expansion, num_classes)
        self._init_weights()

    def _make_layer(self, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes * Bottleneck.expansion:
            downsample = nn.Sequential(
                nn.Conv2d(self.inplanes, planes * Bottleneck.expansion, kernel_size=1, stride=stride, bias=False),
                nn.BatchNorm2d(planes * Bottleneck.expansion),
            )
        layers = [Bottleneck(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes * Bottleneck.expansion
        layers += [Bottleneck(self.inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def _init_weights(self) -> None:
        # torchvision's initialisation, so random-weight runs have realistic activation scales.
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(n, 3, H, W) normalised images → (n, 2048) pooled features."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return torch.flatten(self.avgpool(x), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.features(x))


def random_resnet50(seed: int = 0) -> ResNet50:
    """A ResNet-50 with torchvision's random initialisation from `seed` (eval mode), for tests and timing."""
    generator_state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        model = ResNet50()
    finally:
        torch.random.set_rng_state(generator_state)
    return model.eval()


def load_resnet50(weights_path: str | Path) -> ResNet50:
    """ResNet-50 with a torchvision state_dict checkpoint loaded strictly (eval mode)."""
    path = Path(weights_path)
    if not path.is_file():
        raise FileNotFoundError(f"weights_path {str(path)!r} is not a file")
    # weights_only: a checkpoint is data; never run pickled code from it.
    state = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    model = ResNet50()
    model.load_state_dict(state, strict=True)
    return model.eval()


def find_resnet50_weights(configured: str | Path | None) -> Path | None:
    """Where ImageNet ResNet-50 weights are: the configured path, else torch's hub cache, else None.

    A configured path that does not exist is an error, not a silent fallback.
    The cache searched is `torch.hub.get_dir()/checkpoints/resnet50*.pth`
    (where torchvision's `resnet50(weights=...)` downloads to); the first in
    sorted order wins.
    """
    if configured is not None:
        path = Path(configured).expanduser()
        if not path.is_file():
            raise FileNotFoundError(f"resnet50_weights {str(path)!r} is not a file")
        return path
    checkpoints = Path(torch.hub.get_dir()) / "checkpoints"
    found = sorted(checkpoints.glob("resnet50*.pth")) if checkpoints.is_dir() else []
    return found[0] if found else None


class ResNet50Trunk(nn.Module):
    """(n, 3, H, W) normalised images → (n, 2048) pooled features (no classifier)."""

    def __init__(self, net: ResNet50) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net.features(x)
