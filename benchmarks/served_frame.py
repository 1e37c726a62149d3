"""What one camera frame costs the service: decode + the served model's visual vector, against the default.

    python -m benchmarks.served_frame [--image PATH] [--repeats 15] [--threads 1] [--out FILE.json]

The service decodes a posted JPEG (`load_image`) and computes `visual_features` with the configuration its
model's card names, on one onnxruntime thread by default (`HAPTICLINK_VISUAL_THREADS`). This times exactly
that path for the served configuration (`SERVED_VISUAL`: 2×2 patches, no GLCM, the int8 backbone) and for the
default one (7×7 + GLCM on the fp32 backbone, what models trained before it read), interleaved, after a warm-up,
with the floor in the same run: the served backbone alone on the served configuration's 4 patches (the library
call nothing can undercut).
Medians in ms; the machine's load average is recorded before and after.
"""

from __future__ import annotations

import argparse
import io
import os
import random
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report
from models.offline.provenance import file_input

DEFAULT_OUT = Path("reports") / "bench" / "served_frame.json"
DEFAULT_IMAGE = Path("..") / "shared" / "data" / "hatt-texnet" / "images"
TARGET_MS = 50.0


def frame_bytes(path: Path | None) -> tuple[bytes, str]:
    """A JPEG to post: the given file, the first HaTT photo if ../shared is there, else a synthetic 1024² frame."""
    if path is None and DEFAULT_IMAGE.is_dir():
        path = next(iter(sorted(p for p in DEFAULT_IMAGE.rglob("*") if p.suffix.lower() in (".jpg", ".png"))), None)
    if path is not None:
        return path.read_bytes(), str(path)
    from PIL import Image

    pixels = (np.random.default_rng(0).random((1024, 1024)) * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="JPEG", quality=90)
    return buf.getvalue(), "synthetic 1024×1024 (seed 0)"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.served_frame", description=__doc__.split("\n")[0])
    parser.add_argument("--image", type=Path, help="a JPEG/PNG frame (default: the first HaTT photo, or synthetic)")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (the service's default 1)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.threads < 1:
        parser.error("--repeats and --threads must be ≥ 1")

    from models.offline.featurize import SERVED_VISUAL, backbone_onnx
    from models.visual.config import VisualConfig
    from models.visual.embedding import visual_features
    from models.visual.image import load_image
    from models.visual.onnx_backbone import OnnxBackbone
    from models.visual.patches import extract_patches

    data, source = frame_bytes(args.image)
    configs = {"served (2×2, no GLCM)": SERVED_VISUAL, "default (7×7 + GLCM)": VisualConfig()}
    # each configuration on its own backbone file (the served one is int8, the default fp32)
    backbones = {name: OnnxBackbone(backbone_onnx(c), intra_op_threads=args.threads) for name, c in configs.items()}
    backbone = backbones["served (2×2, no GLCM)"]
    gray = load_image(data, min_size=SERVED_VISUAL.patch_size)
    floor_patches = extract_patches(gray, SERVED_VISUAL.patch_size, SERVED_VISUAL.grid)

    steps = {
        "decode": lambda: load_image(data, min_size=SERVED_VISUAL.patch_size),
        "backbone floor (4 patches)": lambda: backbone.embed(floor_patches),
        **{
            f"frame: {name}": (
                lambda c=c, b=backbones[name]: visual_features(load_image(data, min_size=c.patch_size), c, b)
            )
            for name, c in configs.items()
        },
    }
    for fn in steps.values():  # warm-up: the first call allocates
        fn()
    load_before = list(os.getloadavg())
    samples: dict[str, list[float]] = {k: [] for k in steps}
    order = list(steps)
    rng = random.Random(0)
    for _ in range(args.repeats):
        rng.shuffle(order)
        for k in order:
            t0 = time.perf_counter()
            steps[k]()
            samples[k].append((time.perf_counter() - t0) * 1e3)
    medians = {k: statistics.median(v) for k, v in samples.items()}
    served = medians["frame: served (2×2, no GLCM)"]
    result = {
        "benchmark": "served_frame",
        "command": " ".join(["python -m benchmarks.served_frame", *(argv if argv is not None else sys.argv[1:])]),
        "timestamp": datetime.now(UTC).isoformat(timespec="seconds"),
        "image": {"source": source, "shape": list(gray.shape), "bytes": len(data)},
        "threads": args.threads,
        "repeats": args.repeats,
        "median_ms": medians,
        "samples_ms": samples,
        "served_vs_default": medians["frame: default (7×7 + GLCM)"] / served,
        "served_vs_floor": served / medians["backbone floor (4 patches)"],
        "target_ms": TARGET_MS,
        "target_met": served <= TARGET_MS,
        "configs": {name: c.computation() for name, c in configs.items()},
        "load_before": load_before,
        "load_after": list(os.getloadavg()),
    }
    write_report(args.out, result, [file_input("image", args.image)] if args.image else ())
    print(f"one frame, {args.threads} thread(s), {source} {gray.shape[1]}×{gray.shape[0]}, median of {args.repeats}:")
    for k, v in medians.items():
        print(f"  {k:32s} {v:8.1f} ms")
    print(
        f"served frame {served:.1f} ms (target ≤ {TARGET_MS:g}: {'met' if result['target_met'] else 'MISSED'}); "
        f"{result['served_vs_default']:.1f}× cheaper than the default; {result['served_vs_floor']:.2f}× the backbone "
        f"floor; load {load_before[0]:.1f} → {result['load_after'][0]:.1f}"
    )
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
