"""An int8 copy of an exported ONNX backbone (onnxruntime static quantization, QDQ, per-channel weights).

The copy is built from the fp32 file alone, deterministically: percentile calibration over patches of the
synthetic world's photos (texture_library.procedural), never over a real dataset's photos, so no image a
model is scored on shapes the quantization ranges. It keeps the fp32 file's input, output and metadata,
except its backbone name (fp32 name + INT8_SUFFIX) and its weights fingerprint (of the recipe and the fp32
fingerprint), so features computed with it are cached apart from fp32 ones.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from models.visual.onnx_backbone import (
    INPUT_NAME,
    META_PREFIX,
    PROBE_KEY,
    SOURCE_FILE_KEY,
    SOURCE_FINGERPRINT_KEY,
    SOURCE_NAME_KEY,
)
from models.visual.patches import extract_patches

INT8_SUFFIX = "_int8"
# The calibration set: CALIBRATION_IMAGES procedural photos of CALIBRATION_SIZE² pixels (a camera frame's
# scale: HaTT-like 1024² frames), each cut into a 2×2 grid of 224-px patches as the served configuration cuts
# a frame, fed CALIBRATION_BATCH patches per run.
CALIBRATION_IMAGES = 24
CALIBRATION_SIZE = 1024
CALIBRATION_SEED = 0
CALIBRATION_GRID = 2
CALIBRATION_BATCH = 8
PATCH_SIZE = 224
# Changing anything in the recipe changes the fingerprint (and so every cache key); bump on code changes too
# (2: the first convolutions fp32; 3: min-max calibration with them).
RECIPE_VERSION = 3
# The int8 types onnxruntime's kernels can run (activations, weights): "u8s8" is the fastest where VNNI is
# present and saturates where it is not (AVX2, AVX-512 without VNNI); reduce_range (7-bit weights) and u8u8
# avoid that saturation at a cost (benchmarks/backbone_int8.py --recipes measures each per ISA class).
RECIPES = ("u8s8", "u8s8_reduce_range", "s8s8", "u8u8")
DEFAULT_RECIPE = "u8s8"
# The first FP32_CONVS convolutions (the stem and the first two blocks, at 112² resolution: ≈ 12 % of the
# backbone's multiply-adds) stay fp32. Quantized, they cost the most fidelity (frame cosine to fp32 on held-out
# synthetic photos down to 0.91 with VNNI) and are where u8s8 saturates without it (0.73 on a probe frame under
# qemu's Haswell); kept fp32, the hardest frames measured 0.97–0.99 (3 convolutions: 0.96; 9: no better than 6;
# docs/models.md, "The int8 backbone").
FP32_CONVS = 6


def _calibration(name: str, methods: type) -> dict:
    """quantize_static's calibration arguments for the recipe's `calibration` entry; methods: CalibrationMethod."""
    if name == "min-max":
        return {"calibrate_method": methods.MinMax}
    percentile = float(name.removeprefix("percentile "))
    return {"calibrate_method": methods.Percentile, "extra_options": {"CalibPercentile": percentile}}


def recipe(kind: str = DEFAULT_RECIPE, fp32_convs: int = FP32_CONVS) -> dict:
    """What determines the int8 file besides the fp32 one (hashed into its fingerprint); fp32_convs: how many
    leading convolutions stay fp32 (0: every one quantized, the recipe before version 2)."""
    if kind not in RECIPES:
        raise ValueError(f"int8 recipe must be one of {RECIPES}, got {kind!r}")
    if fp32_convs < 0:
        raise ValueError(f"fp32_convs must be ≥ 0, got {fp32_convs}")
    activations, weights = ("int8", "int8") if kind == "s8s8" else ("uint8", "uint8" if kind == "u8u8" else "int8")
    return {
        # version 1 kept every convolution int8: with fp32_convs=0 its fingerprints stay as they were
        "version": RECIPE_VERSION if fp32_convs else 1,
        "format": "QDQ",
        "weights": f"{weights} per-channel",
        "activations": f"{activations} per-tensor",
        **({"reduce_range": True} if kind == "u8s8_reduce_range" else {}),
        **({"fp32_convs": fp32_convs} if fp32_convs else {}),
        "calibration": "min-max" if fp32_convs else "percentile 99.999",
        "images": CALIBRATION_IMAGES,
        "size": CALIBRATION_SIZE,
        "seed": CALIBRATION_SEED,
        "grid": CALIBRATION_GRID,
    }


def int8_fingerprint(fp32_fingerprint: str, kind: str = DEFAULT_RECIPE, fp32_convs: int = FP32_CONVS) -> str:
    """16 hex digits naming the int8 weights: sha256 of the fp32 fingerprint and the recipe."""
    text = json.dumps({"fp32": fp32_fingerprint, "recipe": recipe(kind, fp32_convs)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def synthetic_patches(
    n_images: int = CALIBRATION_IMAGES, size: int = CALIBRATION_SIZE, seed: int = CALIBRATION_SEED
) -> np.ndarray:
    """(n_images · grid², 224, 224) float32 in [0, 1]: 2×2 patches of procedural texture photos (seeded)."""
    from texture_library.procedural import render_image, sample_params

    root = np.random.default_rng(seed)
    out = []
    for _ in range(n_images):
        rng = np.random.default_rng(root.integers(2**63))
        img = render_image(sample_params(rng), rng, size).astype(np.float32) / 255.0
        out.append(extract_patches(img, PATCH_SIZE, CALIBRATION_GRID))
    return np.concatenate(out)


class _PatchReader:
    """onnxruntime's CalibrationDataReader over a fixed patch array, CALIBRATION_BATCH patches per item."""

    def __init__(self, patches: np.ndarray) -> None:
        self._batches: Iterator[np.ndarray] = iter(
            [patches[i : i + CALIBRATION_BATCH] for i in range(0, len(patches), CALIBRATION_BATCH)]
        )

    def get_next(self) -> dict[str, np.ndarray] | None:
        batch = next(self._batches, None)
        return None if batch is None else {INPUT_NAME: batch}


def quantize_backbone_onnx(
    fp32_path: str | Path,
    out_path: str | Path,
    patches: np.ndarray | None = None,
    kind: str = DEFAULT_RECIPE,
    fp32_convs: int = FP32_CONVS,
) -> Path:
    """Write the int8 copy of the backbone at `fp32_path` to `out_path`; returns `out_path`.

    patches  calibration patches (n, 224, 224) float32 in [0, 1]; default `synthetic_patches()` (tests pass
             fewer; the fingerprint names the default recipe, so only the default belongs in a cache)
    kind     one of RECIPES (the int8 types of activations and weights)
    fp32_convs  leading convolutions (graph order) left fp32
    """
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    fp32 = onnx.load(str(fp32_path))
    meta = {p.key: p.value for p in fp32.metadata_props}
    name_key, fingerprint_key = META_PREFIX + "backbone", META_PREFIX + "weights_fingerprint"
    if name_key not in meta or fingerprint_key not in meta:
        raise ValueError(f"{fp32_path}: not a hapticlink visual backbone (metadata lacks name or fingerprint)")
    if meta[name_key].endswith(INT8_SUFFIX):
        raise ValueError(f"{fp32_path}: already quantized ({meta[name_key]})")
    if PROBE_KEY not in meta:
        # the copy's load-time check compares it with the fp32 file's embeddings: an fp32 file without them is
        # from before probes were stored, and is exported again (featurize.backbone_onnx names it anew)
        raise ValueError(f"{fp32_path}: carries no probe (metadata lacks {PROBE_KEY}); export it again")
    spec = recipe(kind, fp32_convs)
    calibration = synthetic_patches() if patches is None else patches
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        # Shape inference + constant folding first, as onnxruntime recommends: the quantizer then sees
        # every tensor's shape and quantizes the folded Conv weights, not their unfused pieces.
        prepped = Path(tmp) / "prepped.onnx"
        quant_pre_process(str(fp32_path), str(prepped), skip_symbolic_shape=False)
        convs = [n.name for n in onnx.load(str(prepped)).graph.node if n.op_type == "Conv"]
        # The percentile calibrator prints its progress to stdout; a study's log is no place for it.
        with contextlib.redirect_stdout(io.StringIO()):
            quantize_static(
                str(prepped),
                str(out),
                _PatchReader(calibration),
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                # uint8 activations: onnxruntime's u8s8 kernels ran ≈ 2.1× faster than fp32 here (AVX-512 VNNI)
                # against ≈ 1.4× for s8s8, at the same fidelity. With the first blocks fp32, min-max ranges hold the
                # hardest held-out frame at 0.986 against percentile 99.999's 0.968 (recipe 1, every convolution
                # int8, fit percentile better: docs/models.md)
                activation_type=QuantType.QInt8 if spec["activations"].startswith("int8") else QuantType.QUInt8,
                weight_type=QuantType.QUInt8 if spec["weights"].startswith("uint8") else QuantType.QInt8,
                reduce_range=bool(spec.get("reduce_range", False)),
                nodes_to_exclude=convs[:fp32_convs],
                **_calibration(spec["calibration"], CalibrationMethod),
            )
    model = onnx.load(str(out))
    # the fp32 file's probe stays (its reference is the fp32 backbone's); the copy names its source, the fallback
    meta[SOURCE_NAME_KEY], meta[SOURCE_FINGERPRINT_KEY] = meta[name_key], meta[fingerprint_key]
    meta[SOURCE_FILE_KEY] = Path(fp32_path).name
    meta[name_key] = meta[name_key] + INT8_SUFFIX
    meta[fingerprint_key] = int8_fingerprint(meta[fingerprint_key], kind, fp32_convs)
    del model.metadata_props[:]
    for key, value in sorted(meta.items()):
        prop = model.metadata_props.add()
        prop.key, prop.value = key, value
    onnx.save(model, str(out))
    return out
