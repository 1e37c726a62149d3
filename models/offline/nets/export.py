"""ONNX export of a trained network with its standardization folded in.

The exported graph takes RAW features and returns bipolar ratings:

    inputs:  tactile (N, F) float32, visual (N, D) float32   (N dynamic)
    output:  ratings (N, 4) float32 = clip(net(z_t, z_v) · σ_y + μ_y, −100, 100),
             z = clip((x − μ)/σ, ±Z_CLIP) per input (models.inference.standardize)

Only the inputs the model reads are graph inputs: a tactile-only model has just
``tactile``, a visual-only one just ``visual``. The service reads the input names from
the session (and the ``inputs`` metadata entry says the same), so it never has to feed
a dummy tensor. The autoencoder's reconstruction is not exported.

Metadata is written and read by `models.inference.modelfile` (onnxruntime only, no torch); torch is
imported inside `export_onnx`.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, Unpack

import numpy as np

from models.inference.modelfile import write_metadata
from models.inference.standardize import Z_CLIP
from texture_library.attributes import RATING_MAX, RATING_MIN

if TYPE_CHECKING:
    from torch import nn

INPUTS_BY_MODALITY: dict[str, tuple[str, ...]] = {
    "both": ("tactile", "visual"),
    "tactile": ("tactile",),
    "visual": ("visual",),
}
OUTPUT_NAME = "ratings"
OPSET = 17


def _stat_vector(name: str, values: Any, length: int | None, *, positive: bool) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if length is not None and arr.shape[0] != length:
        raise ValueError(f"{name} has {arr.shape[0]} values, the model expects {length}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite values")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0 everywhere (indices {np.flatnonzero(arr <= 0)[:5].tolist()} are not)")
    return arr.astype(np.float32)


def _wrap(model: nn.Module, modality: str, stats: dict[str, np.ndarray]) -> nn.Module:
    """The model between raw-input standardization and output de-standardization."""
    import torch
    from torch import nn

    def _z(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
        return torch.clamp((x - mean) / std, -Z_CLIP, Z_CLIP)  # as models.inference.standardize.Standardizer

    class RawIO(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = model
            for key, value in stats.items():
                self.register_buffer(key, torch.from_numpy(value))

        def _ratings(self, tactile: torch.Tensor | None, visual: torch.Tensor | None) -> torch.Tensor:
            # a branch the model does not read gets a 1-column placeholder: never touched
            batch_ref = tactile if tactile is not None else visual
            assert batch_ref is not None
            t = _z(tactile, self.tactile_mean, self.tactile_std) if tactile is not None else batch_ref[:, :1]
            v = _z(visual, self.visual_mean, self.visual_std) if visual is not None else batch_ref[:, :1]
            y = self.net(t, v)["ratings"] * self.target_std + self.target_mean
            return torch.clamp(y, RATING_MIN, RATING_MAX)

    class Both(RawIO):
        def forward(self, tactile: torch.Tensor, visual: torch.Tensor) -> torch.Tensor:
            return self._ratings(tactile, visual)

    class TactileOnly(RawIO):
        def forward(self, tactile: torch.Tensor) -> torch.Tensor:
            return self._ratings(tactile, None)

    class VisualOnly(RawIO):
        def forward(self, visual: torch.Tensor) -> torch.Tensor:
            return self._ratings(None, visual)

    return {"both": Both, "tactile": TactileOnly, "visual": VisualOnly}[modality]()


class Standardization(TypedDict):
    """The training fold's standardization, given to `raw_model` and `export_onnx` as keywords:
    tactile_mean/std (F,), visual_mean/std (D,), target_mean/std (4,); stds must be > 0."""

    tactile_mean: Any
    tactile_std: Any
    visual_mean: Any
    visual_std: Any
    target_mean: Any
    target_std: Any


def raw_model(
    model: nn.Module,
    *,
    tactile_dim: int | None = None,
    visual_dim: int | None = None,
    **standardization: Unpack[Standardization],
) -> nn.Module:
    """The torch module that `export_onnx` exports: raw inputs (only those the model reads,
    in the order tactile, visual) → bipolar ratings (N, 4), clipped to ±100.

    Returned in eval mode, which also puts ``model`` (held inside it) in eval mode."""
    tactile_mean, tactile_std = standardization["tactile_mean"], standardization["tactile_std"]
    visual_mean, visual_std = standardization["visual_mean"], standardization["visual_std"]
    target_mean, target_std = standardization["target_mean"], standardization["target_std"]
    modality = getattr(model, "modality", None)
    if modality not in INPUTS_BY_MODALITY:
        raise ValueError(f"model has no valid modality attribute (got {modality!r})")
    stats = {
        "tactile_mean": _stat_vector("tactile_mean", tactile_mean, tactile_dim, positive=False),
        "tactile_std": _stat_vector("tactile_std", tactile_std, tactile_dim, positive=True),
        "visual_mean": _stat_vector("visual_mean", visual_mean, visual_dim, positive=False),
        "visual_std": _stat_vector("visual_std", visual_std, visual_dim, positive=True),
        "target_mean": _stat_vector("target_mean", target_mean, 4, positive=False),
        "target_std": _stat_vector("target_std", target_std, 4, positive=True),
    }
    for kind in ("tactile", "visual"):
        if stats[f"{kind}_mean"].shape != stats[f"{kind}_std"].shape:
            raise ValueError(f"{kind}_mean and {kind}_std have different lengths")
    return _wrap(model, modality, stats).eval()


def mean_of(members: list[nn.Module]) -> nn.Module:
    """One raw-IO module averaging the ratings of several (an ensemble of seeds): same inputs, same output."""
    import torch
    from torch import nn

    class MeanOf(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.members = nn.ModuleList(members)

        def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
            return torch.stack([m(*inputs) for m in self.members]).mean(dim=0)

    return MeanOf().eval()


def export_onnx(
    model: nn.Module,
    path: str | Path,
    *,
    metadata: Mapping[str, str],
    **standardization: Unpack[Standardization],
) -> Path:
    """Write ``model`` as ONNX (opset 17) taking raw features and returning bipolar ratings.

    standardization: tactile_mean/std (F,), visual_mean/std (D,), target_mean/std (4,) — the training
    fold's (`Standardization`); stds must be > 0. ``metadata`` values must be strings; the
    entries ``modality`` and ``inputs`` (comma-separated graph input names) are added
    (a caller's value for them must agree). Returns ``path``.
    """
    modality = getattr(model, "modality", None)
    if modality not in INPUTS_BY_MODALITY:
        raise ValueError(f"model has no valid modality attribute (got {modality!r})")
    was_training = model.training
    try:
        wrapped = raw_model(model, **standardization)
        widths = {
            "tactile": np.size(standardization["tactile_mean"]),
            "visual": np.size(standardization["visual_mean"]),
        }
        return export_raw(wrapped, modality, path, metadata, widths)
    finally:
        model.train(was_training)


def export_raw(
    wrapped: nn.Module, modality: str, path: str | Path, metadata: Mapping[str, str], widths: dict[str, int]
) -> Path:
    """Trace a raw-IO module (see `raw_model`; or several averaged) to ONNX and stamp its metadata.

    widths: feature count of each graph input ("tactile", "visual") the module reads.
    """
    import torch

    bad = [k for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise ValueError(f"metadata keys and values must be strings; not so for {bad}")
    inputs = INPUTS_BY_MODALITY[modality]
    own = {"modality": modality, "inputs": ",".join(inputs)}
    clash = {k: metadata[k] for k in own if k in metadata and metadata[k] != own[k]}
    if clash:
        raise ValueError(f"metadata {clash} contradicts the model ({own})")
    # tracing example: batch 2 of zeros (the values do not matter, the batch is dynamic)
    example = tuple(torch.zeros(2, int(widths[n])) for n in inputs)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        # the TorchScript exporter is deprecated but unrolls the ConvLSTM loop into a flat,
        # fast graph; its tracer warnings about shape checks are expected
        warnings.simplefilter("ignore")
        torch.onnx.export(
            wrapped.eval(),
            example,
            str(path),
            input_names=list(inputs),
            output_names=[OUTPUT_NAME],
            dynamic_axes={name: {0: "batch"} for name in (*inputs, OUTPUT_NAME)},
            opset_version=OPSET,
            dynamo=False,
            do_constant_folding=True,
        )
    write_metadata(path, {**metadata, **own})
    return path
