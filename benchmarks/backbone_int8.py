"""The served frame under onnxruntime session options and with the int8 backbone, against fp32, interleaved.

    python -m benchmarks.backbone_int8 [--image PATH] [--images DIR] [--repeats 31] [--out FILE.json]
    python -m benchmarks.backbone_int8 --recipes [--no-timing] [--label TEXT] [--out FILE.json]

Every variant times the service's whole frame on one intra-op thread: decode the posted image (`load_image`)
and compute the served configuration's visual vector (`SERVED_VISUAL`: 2×2 patches, no GLCM). Variants:
fp32 with onnxruntime's defaults (graph optimisation ENABLE_ALL, the 4 patches in one run) — the served path —
then lower optimisation levels, one run per patch, thread spinning off, denormals flushed to zero, and the
int8 copy (models.offline.backbones.quantize). All run in one random order per repeat after a warm-up, so load
on a shared machine hits them alike; medians in ms and ratios to fp32 in the same run. With --images, the int8
embeddings of those photos are compared with fp32's (cosine per patch and per frame mean).

--recipes measures every int8 recipe (models.offline.backbones.quantize.RECIPES) instead, on the CPU it runs on:
frame-mean cosine to fp32 on held-out synthetic photos (HELD_OUT_*: other photos than the calibration's) and the
backbone's time on a frame's 4 patches against fp32's, interleaved; the report names the host and the ISA class
onnxruntime's int8 kernels dispatch on (numpy's cpuid probe). Under an emulator (`qemu-x86_64 -cpu Haswell`,
AVX2 without AVX-512 or VNNI) the cosines are the CPU's; the times are the emulator's and mean nothing
(--no-timing). The int8 files are built once, natively (quantization itself is then no emulated computation),
in the backbone cache ($HAPTICLINK_CACHE); an emulated run reuses them.
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
RECIPES_OUT = Path("reports") / "bench" / "backbone_int8_recipes.json"
BASELINE = "fp32 (served: ENABLE_ALL, batch of 4)"


class SessionEmbedder:
    """A PatchEmbedder over an onnxruntime session built with explicit options (the benchmark's variants).

    path: a hapticlink backbone .onnx; one_by_one: one run per patch instead of one for the batch."""

    def __init__(self, path: Path, options: ort.SessionOptions, one_by_one: bool = False) -> None:
        from models.visual.onnx_backbone import OnnxBackbone

        meta = OnnxBackbone(path, intra_op_threads=1, min_probe_cosine=None)  # validates the file, reads its metadata
        self.name, self.dim, self.fingerprint, self.path = meta.name, meta.dim, meta.fingerprint, path
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


# Held-out synthetic photos for --recipes: 12 procedural 1024² photos, seed 1 (the calibration uses seed 0).
HELD_OUT_IMAGES = 12
HELD_OUT_SIZE = 1024
HELD_OUT_SEED = 1
# numpy's names; it has no probe for AVX-VNNI (the 256-bit VNNI of Alder Lake and later), which /proc/cpuinfo names
_ISA_FEATURES = ("SSE41", "AVX2", "FMA3", "AVX512F", "AVX512BW", "AVX512VNNI", "AVX512BF16")


def host_isa() -> dict:
    """The CPU this process runs on: the x86 features cpuid reports to this process (numpy's runtime probe: an
    emulator's CPU model shows here) and the class onnxruntime's int8 GEMM dispatches on (MLAS: AVX-512 VNNI,
    AVX-512 without VNNI, AVX2), with the host's model name and flags from /proc/cpuinfo, which under qemu-user
    are the host's, not the emulated CPU's. numpy has no probe for AVX-VNNI (256-bit VNNI, which MLAS also uses),
    so an AVX2 class with "avx_vnni" among the flags of a native run means VNNI kernels."""
    import platform

    import numpy as np

    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    cpuinfo = Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").is_file() else []
    model = next(
        (line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")), platform.processor()
    )
    flags = next((line for line in cpuinfo if line.startswith("flags")), "").split()
    seen = {k: bool(features.get(k, False)) for k in _ISA_FEATURES}
    if seen["AVX512VNNI"] and seen["AVX512BW"]:
        isa = "avx512-vnni"
    elif seen["AVX512BW"]:
        isa = "avx512 (no vnni)"
    elif seen["AVX2"]:
        isa = "avx2 (no avx512)"
    else:
        isa = "sse"
    vnni_flags = [f for f in flags if "vnni" in f]
    return {
        "cpu_model": model,
        "cpuid": seen,
        "isa_class": isa,
        "proc_cpuinfo_vnni_flags": vnni_flags,
        "numpy": np.__version__,
    }


def recipe_variants() -> dict[str, tuple[str, int]]:
    """What --recipes measures: {label: (quantize.RECIPES kind, leading convolutions kept fp32)}: the served recipe
    ("u8s8": its first blocks fp32) and each kind with every convolution int8 (recipe 1)."""
    from models.offline.backbones.quantize import DEFAULT_RECIPE, FP32_CONVS, RECIPES

    return {DEFAULT_RECIPE: (DEFAULT_RECIPE, FP32_CONVS), **{f"{k} all-int8": (k, 0) for k in RECIPES}}


def held_out_patches(n_images: int) -> np.ndarray:
    """The 2×2 patches of the first `n_images` held-out photos, (4 · n_images, 224, 224) float32; kept in the
    backbone cache, so an emulated run reads them instead of rendering them under the emulator."""
    from models.offline.backbones.quantize import synthetic_patches
    from models.offline.featurize import cache_root

    path = cache_root() / "backbones" / f"held-out-{n_images}x{HELD_OUT_SIZE}-s{HELD_OUT_SEED}.npy"
    if path.is_file():
        return np.load(path)
    patches = synthetic_patches(n_images, HELD_OUT_SIZE, seed=HELD_OUT_SEED)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, patches)
    return patches


def built_files(folder: Path, config_hash: str) -> tuple[Path, dict[str, Path]]:
    """(the fp32 EfficientNet-Lite0 file, {recipe: its int8 copy}) among the backbone files in `folder` exported for
    `config_hash`, told apart by their metadata (no torch, no quantization: what an emulated run reuses)."""
    from models.offline.backbones.quantize import INT8_SUFFIX, int8_fingerprint
    from models.visual.onnx_backbone import OnnxBackbone

    found = [OnnxBackbone(p, min_probe_cosine=None) for p in sorted(folder.glob("*.onnx"))]
    found = [b for b in found if b.config_hash == config_hash and b.name.startswith("efficientnet_lite0")]
    fp32 = [b for b in found if b.name == "efficientnet_lite0"]
    if len(fp32) != 1:
        raise ValueError(f"{folder}: {len(fp32)} fp32 EfficientNet-Lite0 files for visual config {config_hash}")
    by_fingerprint = {b.fingerprint: b.path for b in found if b.name.endswith(INT8_SUFFIX)}
    wanted = {label: int8_fingerprint(fp32[0].fingerprint, *v) for label, v in recipe_variants().items()}
    files = {k: by_fingerprint[f] for k, f in wanted.items() if f in by_fingerprint}  # the ones built so far
    return fp32[0].path, files


def measure_recipes(timing: bool, repeats: int, n_images: int = HELD_OUT_IMAGES, built: Path | None = None) -> dict:
    """Every int8 recipe against fp32 on this CPU: frame-mean cosine on `n_images` held-out synthetic photos (min,
    median, each), the load-time check each file runs (onnx_backbone.ProbeCheck: what the service would decide
    here) and, when `timing`, the backbone's median time on one frame's 4 patches as a ratio to fp32's.
    built: a folder of files built before (`built_files`) instead of the backbone cache (which builds them)."""
    from models.offline.featurize import INT8_BACKBONE, SERVED_VISUAL, backbone_onnx, int8_backbone_onnx
    from models.visual.onnx_backbone import OnnxBackbone

    config = SERVED_VISUAL.model_copy(update={"backbone": INT8_BACKBONE})
    if built is None:
        fp32_path = backbone_onnx(SERVED_VISUAL.model_copy(update={"backbone": "efficientnet_lite0"}))
        files = {label: int8_backbone_onnx(config, kind, convs) for label, (kind, convs) in recipe_variants().items()}
    else:
        fp32_path, files = built_files(built, config.hash())
    embedders = {"fp32": SessionEmbedder(fp32_path, options())}
    embedders.update({kind: SessionEmbedder(path, options()) for kind, path in files.items()})
    patches = held_out_patches(n_images)
    per_frame = SERVED_VISUAL.grid**2
    frames = {k: e.embed(patches).reshape(n_images, per_frame, -1).mean(1) for k, e in embedders.items()}
    checks = {k: OnnxBackbone(e.path, intra_op_threads=1).check for k, e in embedders.items()}

    def cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))

    recipes: dict[str, dict] = {}
    for kind in files:
        c = cos(frames["fp32"], frames[kind])
        check = checks[kind]
        recipes[kind] = {
            "frame_cosine": {"min": float(c.min()), "median": float(np.median(c)), "each": c.tolist()},
            "load_check": None if check is None else {"cosines": list(check.cosines), "passed": check.passed},
        }
    if timing:
        one = patches[:per_frame]
        samples = time_interleaved({k: (lambda e=e: e.embed(one)) for k, e in embedders.items()}, repeats)
        medians = {k: statistics.median(v) for k, v in samples.items()}
        for kind in files:
            recipes[kind]["time_vs_fp32"] = medians[kind] / medians["fp32"]
        recipes["fp32"] = {"median_ms": medians["fp32"]}
    return {
        "held_out": {
            "images": HELD_OUT_IMAGES,
            "size": HELD_OUT_SIZE,
            "seed": HELD_OUT_SEED,
            "grid": SERVED_VISUAL.grid,
        },
        "recipes": recipes,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.backbone_int8", description=__doc__.split("\n")[0])
    parser.add_argument("--image", type=Path, help="the frame to time (default: a synthetic 1024² JPEG)")
    parser.add_argument("--images", type=Path, help="a folder of photos to compare int8 with fp32 on (PNG/JPEG)")
    parser.add_argument("--repeats", type=int, default=31)
    parser.add_argument("--out", type=Path, default=None, help=f"default {DEFAULT_OUT} ({RECIPES_OUT} with --recipes)")
    parser.add_argument("--recipes", action="store_true", help="measure every int8 recipe on this CPU")
    parser.add_argument("--no-timing", action="store_true", help="with --recipes: cosines only (under an emulator)")
    parser.add_argument(
        "--held-out", type=int, default=HELD_OUT_IMAGES, help="with --recipes: held-out photos (fewer under emulation)"
    )
    parser.add_argument("--built", type=Path, help="with --recipes: reuse the backbone files in this folder")
    parser.add_argument("--label", default="", help="what ran this, e.g. 'qemu-x86_64 -cpu Haswell (emulated)'")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be ≥ 1")
    if args.recipes:
        return recipes_main(args, argv)
    args.out = args.out or DEFAULT_OUT

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


def recipes_main(args: argparse.Namespace, argv: list[str] | None) -> dict:
    """--recipes: measure, then merge this host's entry into the report (one entry per label and ISA class)."""
    import json

    out = args.out or RECIPES_OUT
    host = host_isa()
    load_before = list(os.getloadavg())
    measured = measure_recipes(not args.no_timing, args.repeats, args.held_out, args.built)
    key = f"{host['isa_class']}{' · ' + args.label if args.label else ''}"
    entry = {
        "command": " ".join(["python -m benchmarks.backbone_int8", *(argv if argv is not None else sys.argv[1:])]),
        "label": args.label,
        "timestamp": datetime.now(UTC).isoformat(timespec="seconds"),
        "host": host,
        "onnxruntime": ort.__version__,
        "threads": 1,
        "repeats": None if args.no_timing else args.repeats,
        "load_before": load_before,
        "load_after": list(os.getloadavg()),
        **measured,
    }
    report = json.loads(out.read_text()) if out.is_file() else {"benchmark": "backbone_int8 --recipes", "hosts": {}}
    report["hosts"][key] = entry
    write_report(out, report)
    print(f"{key}: {host['cpu_model']}, onnxruntime {ort.__version__}")
    for kind, r in measured["recipes"].items():
        c = r.get("frame_cosine")
        t = r.get("time_vs_fp32")
        print(
            f"  {kind:20s}"
            + (f" frame cosine min {c['min']:.3f} median {c['median']:.3f}" if c else f" {r['median_ms']:.1f} ms")
            + (f"  load check {'passes' if r['load_check']['passed'] else 'FAILS'}" if r.get("load_check") else "")
            + (f"  time ×{t:.2f} of fp32" if t is not None else "")
        )
    print(f"wrote {out}")
    return entry


if __name__ == "__main__":
    main()
