"""Export a torch visual backbone to the ONNX file the service runs (`models.visual.onnx_backbone.OnnxBackbone`)."""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path

from models.offline.backbones.cnn import Backbone
from models.visual.onnx_backbone import INPUT_NAME, OUTPUT_NAME, backbone_metadata

DEFAULT_OPSET = 18  # the dynamo exporter's native opset: no version conversion step


def export_backbone_onnx(
    backbone: Backbone,
    path: str | Path,
    *,
    config_hash: str,
    opset: int = DEFAULT_OPSET,
    dynamo: bool = True,
) -> Path:
    """Write `backbone` (patch batch → pooled features) to `path` as ONNX with a dynamic batch axis.

    dynamo  True: torch.export-based exporter (torch's supported path, offline, needs onnxscript);
            False: the legacy TorchScript exporter (faster to run, deprecated in torch ≥ 2.9).
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
