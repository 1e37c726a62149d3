"""The served frame under onnxruntime session options and with the int8 backbone, against fp32, interleaved.

    python -m benchmarks.backbone_int8 [--image PATH] [--images DIR] [--repeats 31] [--out FILE.json]

Every variant times the service's whole frame on one intra-op thread: decode the posted image (`load_image`)
and compute the served configuration's visual vector (`SERVED_VISUAL`: 2×2 patches, no GLCM). Variants:
fp32 with onnxruntime's defaults (graph optimisation ENABLE_ALL, the 4 patches in one run) — the served path —
then lower optimisation levels, one run per patch, thread spinning off, denormals flushed to zero, and the
int8 copy (models.offline.backbones.quantize). All run in one random order per repeat after a warm-up, so load
on a shared machine hits them alike; medians in ms and ratios to fp32 in the same run. With --images, the int8
embeddings of those photos are compared with fp32's (cosine per patch and per frame mean).
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from time import perf_counter

import numpy as np
import onnxruntime as ort

from benchmarks.report_file import write_report
from models.offline.provenance import file_input

DEFAULT_OUT = Path("reports") / "bench" / "backbone_int8.json"
BASELINE = "fp32 (served: ENABLE_ALL, batch of 4)"


class SessionEmbedder:
    """A PatchEmbedder over an onnxruntime session built with explicit options (the benchmark's variants).

    path: a hapticlink backbone .onnx; one_by_one: one run per patch instead of one for the batch."""

    def __init__(self, path: Path, options: ort.SessionOptions, one_by_one: bool = False) -> None:
        from models.visual.onnx_backbone import OnnxBackbone

        meta = OnnxBackbone(path, intra_op_threads=1)  # validates the file and reads its metadata
        self.name, self.dim, self.fingerprint = meta.name, meta.dim, meta.fingerprint
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.one_by_one = one_by_one

    def embed(self, patches: np.ndarray) -> np.ndarray:
        """(n, 224, 224) float32 in [0, 1] → (n, dim) float32."""
        x = np.ascontiguousarray(patches, dtype=np.float32)
        if not self.one_by_one:
            return self.session.run(["features"], {"patches": x})[0]
        return np.concatenate([self.session.run(["features"], {"patches": x[i : i + 1]})[0] for i in range(len(x))])


def options(
    level: ort.GraphOptimizationLevel = ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    spinning: bool = True,
    denormal_zero: bool = False,
) -> ort.SessionOptions:
    """One intra-op thread (the service's default) with the given optimisation level and switches."""
    o = ort.SessionOptions()
    o.intra_op_num_threads = 1
    o.inter_op_num_threads = 1
    o.graph_optimization_level = level
    if not spinning:
        o.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if denormal_zero:
        o.add_session_config_entry("session.set_denormal_as_zero", "1")
    return o


def variants(fp32: Path, int8: Path) -> dict[str, SessionEmbedder]:
    level = ort.GraphOptimizationLevel
    return {
        BASELINE: SessionEmbedder(fp32, options()),
        "fp32 ENABLE_EXTENDED": SessionEmbedder(fp32, options(level.ORT_ENABLE_EXTENDED)),
        "fp32 ENABLE_BASIC": SessionEmbedder(fp32, options(level.ORT_ENABLE_BASIC)),
        "fp32 DISABLE_ALL": SessionEmbedder(fp32, options(level.ORT_DISABLE_ALL)),
        "fp32 one run per patch": SessionEmbedder(fp32, options(), one_by_one=True),
        "fp32 spinning off": SessionEmbedder(fp32, options(spinning=False)),
        "fp32 denormals as zero": SessionEmbedder(fp32, options(denormal_zero=True)),
        "int8 (batch of 4)": SessionEmbedder(int8, options()),
        "int8 one run per patch": SessionEmbedder(int8, options(), one_by_one=True),
    }


def time_interleaved(steps: dict[str, Callable[[], object]], repeats: int, seed: int = 0) -> dict[str, list[float]]:
    """ms per call of every step, `repeats` rounds in a fresh random order each, after one warm-up call each."""
    for fn in steps.values():
        fn()
    samples: dict[str, list[float]] = {k: [] for k in steps}
    order, rng = list(steps), random.Random(seed)
    for _ in range(repeats):
        rng.shuffle(order)
        for k in order:
            t0 = perf_counter()
            steps[k]()
            samples[k].append((perf_counter() - t0) * 1e3)
    return samples


def fidelity(images: list[Path], fp32: SessionEmbedder, int8: SessionEmbedder) -> dict:
    """Cosine of int8 against fp32 embeddings of the served 2×2 patches of `images`: per patch and per frame
    mean (what the model reads), min / 5th percentile / median."""
    from models.offline.featurize import SERVED_VISUAL
    from models.visual.image import load_image
    from models.visual.patches import extract_patches

    def cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))

    patch: list[float] = []
    frame: list[float] = []
    for path in images:
        x = extract_patches(load_image(path, min_size=224), SERVED_VISUAL.patch_size, SERVED_VISUAL.grid)
        a, b = fp32.embed(x), int8.embed(x)
        patch.extend(float(c) for c in cos(a, b))
        frame.append(float(cos(a.mean(0), b.mean(0))))

    def summary(v: list[float]) -> dict:
        return {"min": float(np.min(v)), "p5": float(np.percentile(v, 5)), "median": float(np.median(v))}

    return {"images": len(images), "patch": summary(patch), "frame": summary(frame)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.backbone_int8", description=__doc__.split("\n")[0])
    parser.add_argument("--image", type=Path, help="the frame to time (default: a synthetic 1024² JPEG)")
    parser.add_argument("--images", type=Path, help="a folder of photos to compare int8 with fp32 on (PNG/JPEG)")
    parser.add_argument("--repeats", type=int, default=31)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be ≥ 1")

    from benchmarks.served_frame import frame_bytes
    from models.offline.featurize import INT8_BACKBONE, SERVED_VISUAL, backbone_onnx
    from models.visual.embedding import visual_features
    from models.visual.image import load_image

    fp32_path = backbone_onnx(SERVED_VISUAL.model_copy(update={"backbone": "efficientnet_lite0"}))
    int8_path = backbone_onnx(SERVED_VISUAL.model_copy(update={"backbone": INT8_BACKBONE}))
    embedders = variants(fp32_path, int8_path)
    data, source = frame_bytes(args.image)

    def frame(embedder: SessionEmbedder) -> Callable[[], object]:
        return lambda: visual_features(load_image(data, min_size=224), SERVED_VISUAL, embedder)

    steps: dict[str, Callable[[], object]] = {name: frame(e) for name, e in embedders.items()}
    steps["decode alone"] = lambda: load_image(data, min_size=224)
    load_before = list(os.getloadavg())
    samples = time_interleaved(steps, args.repeats)
    medians = {k: statistics.median(v) for k, v in samples.items()}
    base = medians[BASELINE]
    result = {
        "benchmark": "backbone_int8",
        "command": " ".join(["python -m benchmarks.backbone_int8", *(argv if argv is not None else sys.argv[1:])]),
        "timestamp": datetime.now(UTC).isoformat(timespec="seconds"),
        "image": {"source": source, "bytes": len(data)},
        "threads": 1,
        "repeats": args.repeats,
        "onnxruntime": ort.__version__,
        "backbones": {"fp32": fp32_path.name, "int8": int8_path.name},
        "median_ms": medians,
        "ratio_to_fp32": {k: v / base for k, v in medians.items()},
        "samples_ms": samples,
        "load_before": load_before,
        "load_after": list(os.getloadavg()),
    }
    if args.images is not None:
        photos = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        result["fidelity"] = fidelity(photos, embedders[BASELINE], embedders["int8 (batch of 4)"])
    read = [file_input("image", args.image)] if args.image else []
    read += [file_input("photos", args.images)] if args.images else []
    write_report(args.out, result, read)
    print(f"one served frame (decode + 2×2 patches, no GLCM), 1 thread, {source}, median of {args.repeats}:")
    for k, v in medians.items():
        print(f"  {k:40s} {v:7.1f} ms  ×{v / base:.2f}")
    if "fidelity" in result:
        f = result["fidelity"]
        print(
            f"int8 vs fp32 cosine over {f['images']} photos: frame mean min {f['frame']['min']:.4f} "
            f"median {f['frame']['median']:.4f}; patch min {f['patch']['min']:.4f} median {f['patch']['median']:.4f}"
        )
    print(f"load {load_before[0]:.1f} → {result['load_after'][0]:.1f}; wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
