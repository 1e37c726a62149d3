"""Visual embedding cost per image on CPU: patching, GLCM, and each backbone under torch and onnxruntime.

    python -m benchmarks.visual [--repeats 3] [--threads 1,2] [--image PATH] [--out reports/bench/visual.json]

One image = 49 patches of 224×224 (the default VisualConfig). Backbones:
EfficientNet-Lite0 with its shipped ImageNet weights, ResNet-50 with random
weights (same FLOPs as ImageNet weights). Each backbone is exported to ONNX
with the default exporter into a temporary directory; torch and onnxruntime
runs are interleaved, after one warm-up each, and the median is reported. The
torch/onnxruntime parity on the benchmark patches is recorded too.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.report_file import write_report
from models.offline.provenance import file_input

DEFAULT_OUT = Path("reports") / "bench" / "visual.json"


def time_call(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> list[float]:
    """Wall-clock seconds of `repeats` calls of `fn`, after `warmup` untimed calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return samples


def summarise(samples: list[float]) -> dict[str, Any]:
    """Milliseconds: median, min, max and every sample."""
    ms = [s * 1e3 for s in samples]
    return {"median_ms": statistics.median(ms), "min_ms": min(ms), "max_ms": max(ms), "samples_ms": ms}


def benchmark_image(path: str | None, seed: int) -> np.ndarray:
    """The image to embed: a given file, or a seeded 1024×1024 synthetic texture (HaTT photo size)."""
    from models.visual.image import load_image

    if path is not None:
        return load_image(path)
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:1024, 0:1024]
    grating = 0.5 + 0.2 * np.sin(2 * np.pi * (rows * 0.013 + cols * 0.029))
    return np.clip(grating + rng.normal(0.0, 0.12, size=(1024, 1024)), 0.0, 1.0).astype(np.float32)


def bench_backbone(
    backbone: Any, patches: np.ndarray, config_hash: str, thread_counts: list[int], repeats: int, workdir: Path
) -> list[dict[str, Any]]:
    """Torch vs onnxruntime embedding time of one image's patches at each thread count, plus export time and parity."""
    import torch

    from models.offline.backbones.onnx_export import export_backbone_onnx
    from models.visual.onnx_backbone import OnnxBackbone

    start = time.perf_counter()
    onnx_path = export_backbone_onnx(backbone, workdir / f"{backbone.name}.onnx", config_hash=config_hash)
    export_s = time.perf_counter() - start
    rows = []
    for threads in thread_counts:
        torch.set_num_threads(threads)
        runner = OnnxBackbone(onnx_path, intra_op_threads=threads, batch_size=backbone.batch_size)
        torch_out, ort_out = backbone.embed(patches), runner.embed(patches)  # warm-up, and the parity check
        scale = max(1.0, float(np.abs(torch_out).max()))
        torch_samples: list[float] = []
        ort_samples: list[float] = []
        for _ in range(repeats):  # interleaved, so drifting machine load hits both alike
            torch_samples += time_call(lambda: backbone.embed(patches), 1, warmup=0)
            ort_samples += time_call(lambda r=runner: r.embed(patches), 1, warmup=0)
        torch_stats, ort_stats = summarise(torch_samples), summarise(ort_samples)
        rows.append(
            {
                "backbone": backbone.name,
                "dim": backbone.dim,
                "weights": "imagenet" if backbone.name == "efficientnet_lite0" else "random (same FLOPs)",
                "weights_fingerprint": backbone.fingerprint,
                "threads": threads,
                "patches_per_image": int(patches.shape[0]),
                "batch_size": backbone.batch_size,
                "onnx_export_s": export_s,
                "onnx_file_mb": onnx_path.stat().st_size / 1e6,
                "torch": torch_stats,
                "onnxruntime": ort_stats,
                "ort_speedup": torch_stats["median_ms"] / ort_stats["median_ms"],
                "parity_max_abs_diff": float(np.abs(torch_out - ort_out).max()),
                "parity_feature_scale": scale,
            }
        )
    return rows


def machine_info() -> dict[str, Any]:
    """Where the numbers were taken."""
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "cpus_usable": affinity,
        "loadavg_1_5_15": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def print_table(result: dict[str, Any]) -> None:
    print(
        f"\nvisual embedding per image ({result['config']['n_patches']} patches of "
        f"{result['config']['patch_size']}×{result['config']['patch_size']}), median of {result['repeats']}"
    )
    print(f"{'step':<38}{'threads':>8}{'torch ms':>10}{'onnxruntime ms':>16}{'ort speed-up':>14}{'max |Δ|/scale':>15}")
    for row in result["backbones"]:
        label = f"{row['backbone']} ({row['dim']}-d, {'ImageNet' if row['weights'] == 'imagenet' else 'random'})"
        rel = row["parity_max_abs_diff"] / row["parity_feature_scale"]
        print(
            f"{label:<38}{row['threads']:>8}{row['torch']['median_ms']:>10.0f}{row['onnxruntime']['median_ms']:>16.0f}"
            f"{row['ort_speedup']:>13.2f}×{rel:>15.1e}"
        )
    print(f"{'patch extraction (numpy)':<38}{1:>8}{result['patches']['median_ms']:>10.1f}")
    print(f"{'GLCM 16 levels, 4 angles (numpy)':<38}{1:>8}{result['glcm']['median_ms']:>10.1f}")
    print(f"load average before/after: {result['machine']['loadavg_1_5_15']} / {result['loadavg_after']}")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.visual", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per backbone and runtime (default 3)")
    parser.add_argument(
        "--threads",
        default=None,
        help="comma-separated intra-op thread counts for torch and onnxruntime (default: 1 and torch's default)",
    )
    parser.add_argument("--image", default=None, help="image file to embed (default: synthetic 1024×1024)")
    parser.add_argument("--backbones", default="efficientnet_lite0,resnet50", help="comma-separated subset")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"JSON report (default {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be ≥ 1")

    import onnxruntime
    import torch

    from models.offline.backbones.cnn import efficientnet_lite0_backbone, resnet50_backbone
    from models.visual.config import VisualConfig
    from models.visual.glcm import glcm_features
    from models.visual.patches import extract_patches

    machine = machine_info()
    default_threads = torch.get_num_threads()
    try:
        thread_counts = [int(t) for t in args.threads.split(",")] if args.threads else sorted({1, default_threads})
    except ValueError:
        parser.error(f"--threads must be comma-separated integers, got {args.threads!r}")
    if any(t < 1 for t in thread_counts):
        parser.error(f"--threads must be ≥ 1, got {args.threads!r}")
    config = VisualConfig()
    image = benchmark_image(args.image, seed=0)
    patches = extract_patches(image, config.patch_size, config.grid)

    builders = {"efficientnet_lite0": efficientnet_lite0_backbone, "resnet50": lambda: resnet50_backbone(None, seed=0)}
    names = [n.strip() for n in args.backbones.split(",") if n.strip()]
    unknown = sorted(set(names) - set(builders))
    if unknown:
        parser.error(f"--backbones: unknown {unknown}; choose from {sorted(builders)}")

    rows = []
    with tempfile.TemporaryDirectory(prefix="hapticlink-bench-") as tmp:
        for name in names:
            print(f"benchmarking {name} …", file=sys.stderr, flush=True)
            rows += bench_backbone(builders[name](), patches, config.hash(), thread_counts, args.repeats, Path(tmp))

    result = {
        "benchmark": "visual",
        "command": " ".join(["python -m benchmarks.visual", *(argv if argv is not None else sys.argv[1:])]),
        "timestamp": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": machine,
        "versions": {
            "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__,
            "numpy": np.__version__,
        },
        "threads": {
            "counts": thread_counts,
            "torch_default": default_threads,
            "note": "torch.set_num_threads and onnxruntime intra_op_num_threads set alike per row",
        },
        "repeats": args.repeats,
        "image": {"source": args.image or "synthetic 1024×1024 (seed 0)", "shape": list(image.shape)},
        "config": {
            "patch_size": config.patch_size,
            "grid": config.grid,
            "n_patches": config.n_patches,
            "glcm_levels": config.glcm_levels,
            "hash": config.hash(),
        },
        "patches": summarise(
            time_call(lambda: extract_patches(image, config.patch_size, config.grid), args.repeats * 3)
        ),
        "glcm": summarise(
            time_call(
                lambda: glcm_features(image, config.glcm_levels, config.glcm_distances, config.glcm_angles_deg),
                args.repeats * 3,
            )
        ),
        "backbones": rows,
        "loadavg_after": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    write_report(args.out, result, [file_input("image", args.image)] if args.image else ())
    print_table(result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
