"""Export a torch visual backbone to the ONNX file the service runs (`models.visual.onnx_backbone.OnnxBackbone`)."""

from __future__ import annotations

import contextlib
import functools
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from models.offline.backbones.cnn import Backbone
from models.visual.onnx_backbone import (
    INPUT_NAME,
    OUTPUT_NAME,
    PROBE_KEY,
    backbone_metadata,
    probe_inputs,
    probe_metadata,
)

DEFAULT_OPSET = 18  # the dynamo exporter's native opset: no version conversion step
# The probe every exported backbone carries for its load-time check (onnx_backbone.ProbeCheck): the 2×2 patches
# of PROBE_IMAGES procedural photos of PROBE_SIZE² (seed PROBE_SEED: neither the int8 calibration's seed 0 nor
# the held-out photos' seed 1), the served configuration's cut of a camera frame; ≈ 0.5 MB of metadata.
PROBE_IMAGES = 2
PROBE_SIZE = 1024
PROBE_SEED = 2
PROBE_PER_FRAME = 4


def default_probe_patches() -> np.ndarray:
    """(PROBE_IMAGES · 4, 224, 224) float32 in [0, 1]: the probe patches, frame by frame (a fresh copy)."""
    return _probe_patches().copy()


@functools.cache
def _probe_patches() -> np.ndarray:
    from models.offline.backbones.quantize import synthetic_patches

    return synthetic_patches(PROBE_IMAGES, PROBE_SIZE, seed=PROBE_SEED)


def torch_probe(backbone: Backbone, patches: np.ndarray | None = None) -> str:
    """The PROBE_KEY value for `backbone`: its probe patches and their fp32 frame-mean embeddings by torch."""
    x = probe_inputs(default_probe_patches() if patches is None else patches)
    frames = backbone.embed(x).reshape(-1, PROBE_PER_FRAME, backbone.dim).mean(1)
    return probe_metadata(x, frames, PROBE_PER_FRAME, f"{backbone.name} fp32 (torch)")


def export_backbone_onnx(
    backbone: Backbone,
    path: str | Path,
    *,
    config_hash: str,
    opset: int = DEFAULT_OPSET,
    dynamo: bool = True,
    probe_patches: np.ndarray | None = None,
) -> Path:
    """Write `backbone` (patch batch → pooled features) to `path` as ONNX with a dynamic batch axis.

    dynamo  True: torch.export-based exporter (torch's supported path, offline, needs onnxscript);
            False: the legacy TorchScript exporter (faster to run, deprecated in torch ≥ 2.9).
    probe_patches  the probe's patches, (4k, 224, 224) in [0, 1], frame by frame (default: default_probe_patches())
    returns the written path
    """
    import onnx
    import torch

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    example = torch.rand(2, backbone.input_size, backbone.input_size, generator=torch.Generator().manual_seed(0))
    encoder = backbone.encoder.eval()
    with _quiet_exporter():
        batch: dict = (
            # external_data=False: one self-contained file to ship
            {"dynamic_shapes": {INPUT_NAME: {0: torch.export.Dim("batch")}}, "external_data": False, "verbose": False}
            if dynamo
            else {"dynamic_axes": {INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}}}
        )
        torch.onnx.export(
            encoder,
            (example,),
            str(out),
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            opset_version=opset,
            dynamo=dynamo,
            **batch,
        )
    model = onnx.load(str(out))
    meta = backbone_metadata(backbone.name, backbone.dim, backbone.fingerprint, config_hash, backbone.input_size)
    meta[PROBE_KEY] = torch_probe(backbone, probe_patches)
    existing = {p.key: p for p in model.metadata_props}
    for key, value in meta.items():
        prop = existing.get(key) or model.metadata_props.add()
        prop.key, prop.value = key, value
    onnx.save(model, str(out))
    return out


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    # The exporter logs a warning per missing torchvision op and emits deprecation
    # chatter; none of it concerns this graph. Errors still raise.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            yield
    finally:
        logger.setLevel(level)
