"""Adaptive serving against always running everything, on a stream that strokes a sequence of unseen textures.

    python -m benchmarks.adaptive [--textures 6] [--seconds 6] [--fps 10] [--full ann-ensemble] [--cheap ridge-both]
                                  [--pool-frames 1 3] [--out reports/tradeoffs/adaptive.json]

The data: hatt-texnet (`data/hatt-texnet`, its HaTT models from `--hatt-source` for the library)
when both exist, else the synthetic world (built under data/serving-adaptive-synthetic). `--textures`
rated textures are drawn (seeded) to be *streamed*; the full and the cheap model are trained on the
other rated textures only (`train_and_export(..., exclude=...)`: training, interval calibration and
the OOD detector never see a streamed texture) and cached under cache/adaptive/. The cheap model's
intervals are normalised by feature-space distance, so its width follows the input.

The stream: `--seconds` of each streamed texture's recording, back to back on one clock (20 ms
blocks, 1 kHz), and camera frames at `--fps`: the texture's photo as a camera over the stroked
area sees it — a crop of 94 % of the photo (962 px of HaTT's 1024), shifted by a few pixels from frame to frame
(hand tremor) with sensor noise (σ 0.01), JPEG-encoded; the scene changes when the texture does.

Each policy replays the whole stream through the service's own pieces, one robot, in time order:
frames decoded (`Runtime.decode_frame`) and thumbnail-tested, `SceneViews` deciding what to embed
(`Runtime.embed_and_inspect`, frame checks, pooling), blocks admitted by the `StreamContract`, and
each completed window estimated by `pipeline.estimate_batch` (features, the cheap and/or full model,
OOD check, interval, EMA, nearest, hysteresis) — everything the service computes per second of
stream, without the network. `always-full` embeds every frame and runs the full model on every window
(its visual input: the newest frame's embedding); `adaptive` as `service/adaptive.py` says, once per
`--pool-frames` value. CPU time is the process's (time.process_time; onnxruntime runs one thread).

Accuracy: per window, |smoothed rating − the stroked texture's mean human rating|, on the 0–100
scale (÷ 2), averaged over attributes and windows (the texture at the window's middle); a
texture-level bootstrap (2000 resamples of the streamed textures, seed 0) gives 95 % intervals.
Choice agreement: the fraction of windows whose chosen library model equals always-full's.

Writes `--out` in the shape of the "adaptive" entry of reports/tradeoffs/results.json ({"compute_ratio",
"mae_full", "mae_adaptive", "choice_agreement"} for the Settings' default policy) plus every variant, the targets
and the run.
Timings taken on a shared machine are marked as such by the caller; ratios come from one run.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from PIL import Image

from benchmarks.report_file import write_report

DEFAULT_OUT = Path("reports") / "tradeoffs" / "adaptive.json"
HATT_DATASET = Path("data") / "hatt-texnet"
HATT_SOURCE = Path("..") / "shared" / "data" / "hatt-texnet"  # the licensed raw data (its HaTT models: the library)
SYNTH_ROOT = Path("data") / "serving-adaptive-synthetic"
BLOCK_S = 0.02
CROP = 0.94  # of the photo's shorter side: a 1024 px HaTT photo gives 962 px frames
JITTER_PX = 4
FRAME_NOISE = 0.01
TARGETS = {"compute_ratio": 5.0, "mae_increase": 0.2, "choice_agreement": 0.95}


@dataclass(frozen=True)
class Stream:
    """textures: the streamed ids in order; seconds: per texture; blocks: SampleBlocks; frames: (t, JPEG bytes);
    truth: (T, 4) bipolar mean ratings of the streamed textures."""

    textures: list[str]
    seconds: float
    blocks: list
    frames: list[tuple[float, bytes]]
    truth: np.ndarray


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adaptive", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--textures", type=int, default=6, help="unseen textures streamed one after another (default 6)"
    )
    parser.add_argument("--seconds", type=float, default=6.0, help="seconds of stroking per texture (default 6)")
    parser.add_argument("--fps", type=float, default=10.0, help="camera frames per second (default 10)")
    parser.add_argument("--full", default="ann-ensemble", help="the full (served) model (default ann-ensemble)")
    parser.add_argument("--cheap", default="ridge-both", help="the cheap model (default ridge-both)")
    parser.add_argument("--pool-frames", type=int, nargs="+", default=[1, 3], help="adaptive variants (default 1 3)")
    parser.add_argument(
        "--calibration-folds", type=int, default=10, help="K-fold calibration of both models (default 10)"
    )
    parser.add_argument(
        "--full-calibration-folds",
        type=int,
        default=None,
        help="K of the full model's calibration if other than --calibration-folds (a network costs K more fits)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--synthetic", action="store_true", help="use the synthetic world even if hatt-texnet exists")
    parser.add_argument(
        "--hatt-source",
        type=Path,
        default=HATT_SOURCE,
        help=f"the raw hatt-texnet folder, for the library's HaTT models (default {HATT_SOURCE})",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.textures < 2 or args.seconds < 1.5 or args.fps <= 0:
        parser.error("--textures must be ≥ 2, --seconds ≥ 1.5 and --fps > 0")

    from models.inference.predictor import Predictor
    from models.offline.featurize import backbone_onnx
    from service.settings import Settings

    source, dataset, library = _data(args)
    streamed = _pick(dataset, args.textures, args.seed)
    print(f"data: {source}; streamed (unseen by both models): {', '.join(streamed)}", flush=True)
    full_folds = args.calibration_folds if args.full_calibration_folds is None else args.full_calibration_folds
    full = _model(dataset, args.full, streamed, args, "none", full_folds)
    cheap = _model(dataset, args.cheap, streamed, args, "distance", args.calibration_folds)
    backbone = backbone_onnx(Predictor(full).visual_config)
    stream = _stream(dataset, streamed, args.seconds, args.fps, args.seed)
    print(
        f"stream: {len(streamed)} × {args.seconds:g} s, {len(stream.blocks)} blocks, {len(stream.frames)} frames",
        flush=True,
    )

    base = dict(model_path=full, library_dir=library, backbone_path=backbone, instance_id="bench", api_keys="unused")
    runs = {"always-full": _replay(Settings(**base, serving_policy="always-full"), stream, "always-full")}
    for k in args.pool_frames:
        name = f"adaptive-pool{k}"
        runs[name] = _replay(
            Settings(**base, serving_policy="adaptive", cheap_model_path=cheap, pool_frames=k), stream, name
        )
    reference = runs["always-full"]
    variants = {
        name: _compare(reference, run, stream, args.seed) for name, run in runs.items() if name != "always-full"
    }
    default_pool = Settings.model_fields["pool_frames"].default
    headline_name = (
        f"adaptive-pool{default_pool}" if f"adaptive-pool{default_pool}" in variants else next(iter(variants))
    )
    headline = variants[headline_name]
    result = {
        "compute_ratio": headline["compute_ratio"],
        "mae_full": headline["mae_full"],
        "mae_adaptive": headline["mae_adaptive"],
        "choice_agreement": headline["choice_agreement"],
        "headline": headline_name,
        "targets": TARGETS,
        "meets_targets": _meets(headline),
        "full": {k: v for k, v in reference.items() if k not in ("chosen", "ratings", "texture_of")},
        "variants": {n: {**v, "meets_targets": _meets(v)} for n, v in variants.items()},
        "stream": {
            "source": source,
            "textures": len(streamed),
            "seconds_per_texture": args.seconds,
            "fps": args.fps,
            "stream_s": round(len(streamed) * args.seconds, 3),
            "frames": len(stream.frames),
            "blocks": len(stream.blocks),
        },
        "models": {
            "full": args.full,
            "cheap": args.cheap,
            "calibration_folds": args.calibration_folds,
            "full_calibration_folds": full_folds,
            "trained_on": "every rated texture but the streamed ones",
        },
        "command": "python -m benchmarks.adaptive " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "load_average": list(os.getloadavg()),
            "when": datetime.now(UTC).isoformat(timespec="seconds"),
        },
    }
    _print(result)
    write_report(args.out, result)
    print(f"wrote {args.out}", flush=True)
    return result


# ---- data, models, stream ----------------------------------------------------------------------------
def _data(args) -> tuple[str, Path, Path]:
    """(source name, dataset root, library root); builds what is missing (never inside the repository's git)."""
    if HATT_DATASET.is_dir() and args.hatt_source.is_dir() and not args.synthetic:
        library = Path("cache") / "adaptive" / "hatt-library"
        if not (library / "library.json").is_file():
            from texture_library.hatt_library import import_hatt

            print("importing the HaTT library (human ratings of the rated textures) …", flush=True)
            import_hatt(args.hatt_source, library)
        return "hatt-texnet", HATT_DATASET, library
    from models.offline.datasets.build import build
    from texture_library.synthetic_library import build_synthetic_library

    dataset, library = SYNTH_ROOT / "dataset", SYNTH_ROOT / "library"
    if not (dataset / "dataset.json").is_file():
        print("building a synthetic world of 24 textures …", flush=True)
        build("synthetic", dataset, n_textures=24, seed=args.seed)
    if not (library / "library.json").is_file():
        build_synthetic_library(library, n_textures=24, seed=args.seed)
    return "synthetic", dataset, library


def _pick(dataset: Path, n: int, seed: int) -> list[str]:
    from models.offline.datasets.format import Dataset

    rated = Dataset(dataset).texture_ids("yes")
    if n > len(rated) - 8:
        raise ValueError(f"--textures {n}: {len(rated)} rated textures leave fewer than 8 to train on")
    return sorted(np.random.default_rng(seed).choice(rated, size=n, replace=False).tolist())


def _model(dataset: Path, name: str, streamed: list[str], args, scale: str, folds: int) -> Path:
    """The model trained without the streamed textures (cached by its recipe)."""
    from models.offline.featurize import SERVED_VISUAL
    from models.offline.train import train_and_export

    visual = SERVED_VISUAL.hash()
    key = f"{Path(dataset).name}-{name}-{scale}-k{folds}-s{args.seed}-v{visual}-" + "-".join(streamed)
    out = Path("cache") / "adaptive" / "models" / f"{hashlib.sha256(key.encode()).hexdigest()[:12]}-{name}.onnx"
    recipe = out.with_suffix(".json")
    if out.is_file() and recipe.is_file() and json.loads(recipe.read_text()).get("key") == key:
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    print(f"training {name} on the other rated textures (calibration: {folds}-fold, {scale}) …", flush=True)
    started = time.perf_counter()
    train_and_export(
        dataset,
        name,
        out,
        seed=args.seed,
        visual_config=SERVED_VISUAL,
        calibration_folds=folds,
        interval_scale=scale,
        exclude=tuple(streamed),
    )
    recipe.write_text(json.dumps({"key": key, "train_s": round(time.perf_counter() - started, 1)}))
    return out


def _stream(dataset: Path, textures: list[str], seconds: float, fps: float, seed: int) -> Stream:
    from drivers.source import blocks_from_arrays
    from models.offline.datasets.format import Dataset
    from models.visual.image import load_image

    ds = Dataset(dataset)
    means = ds.mean_ratings()
    rng = np.random.default_rng(seed + 1)
    accel, force, speed, frames = [], [], [], []
    for k, t in enumerate(textures):
        rec = ds.recordings(t)[0]
        for part, ch in ((accel, rec.accel), (force, rec.force), (speed, rec.speed)):
            n = int(round(seconds * ch.rate_hz))
            if len(ch.data) < n:
                raise ValueError(
                    f"{t}: its recording holds {len(ch.data) / ch.rate_hz:.1f} s, fewer than --seconds {seconds}"
                )
            part.append((ch.data[:n], ch.rate_hz))
        photo = load_image(ds.image_paths(t)[0], min_size=256)
        for i in range(int(round(seconds * fps))):
            frames.append((k * seconds + i / fps, _camera_frame(photo, rng)))
    channels = {
        "accel": (np.concatenate([a for a, _ in accel]), accel[0][1], "m/s^2"),
        "force": (np.concatenate([a for a, _ in force]), force[0][1], "N"),
        "speed": (np.concatenate([a for a, _ in speed]), speed[0][1], "mm/s"),
    }
    blocks = list(blocks_from_arrays(channels, BLOCK_S, t0=0.0, seq0=0))
    return Stream(textures, seconds, blocks, frames, np.array([means[t] for t in textures], float))


def _camera_frame(photo: np.ndarray, rng: np.random.Generator) -> bytes:
    """A camera's view of the stroked area: a window of CROP × the photo's side near its centre, shifted by
    ≤ JITTER_PX, with sensor noise, as JPEG (quality 92)."""
    h, w = photo.shape
    side = int(CROP * min(h, w))
    y = (h - side) // 2 + int(rng.integers(-JITTER_PX, JITTER_PX + 1))
    x = (w - side) // 2 + int(rng.integers(-JITTER_PX, JITTER_PX + 1))
    view = np.clip(photo[y : y + side, x : x + side] + rng.normal(0, FRAME_NOISE, (side, side)), 0, 1)
    buf = io.BytesIO()
    Image.fromarray((view * 255).astype(np.uint8)).save(buf, format="JPEG", quality=92)
    return buf.getvalue()


# ---- one policy over the stream --------------------------------------------------------------------
def _replay(settings, stream: Stream, name: str) -> dict:
    """Everything the service computes for this stream under `settings`, in time order (see the docstring)."""
    from drivers.scene_change import thumbnail
    from models.visual.config import VisualConfig  # noqa: F401 - imported before timing
    from service.adaptive import SceneViews
    from service.live_session import canonical_channels, stream_contract
    from service.pipeline import AdmittedBlock, SessionEstimator, SessionJob, estimate_batch
    from service.runtime import load_runtime
    from service.warmup import warm_up

    runtime = load_runtime(settings)
    warm_up(runtime, settings)
    contract = stream_contract(runtime, settings)
    cursor = contract.start()
    estimator = SessionEstimator.from_settings(runtime, contract, settings)
    scene = SceneViews(runtime.policy, settings.frame_change)
    visual, checks = None, {}
    pending: list = []
    windows: list = []
    embeds = escalated = 0
    frames = list(stream.frames)
    fi = 0
    started = time.process_time()
    wall = time.perf_counter()
    for block in stream.blocks:
        block_end = block.t0 + BLOCK_S
        while fi < len(frames) and frames[fi][0] < block_end:  # frames that arrived before this block's end
            gray = runtime.decode_frame(frames[fi][1])
            take, new_scene = scene.offer(thumbnail(gray))
            if take:
                vector, reasons = runtime.embed_and_inspect(gray)
                visual = scene.add(vector, new_scene)
                checks = runtime.frame_checks(reasons, visual)
                embeds += 1
            fi += 1
        adv = contract.admit(cursor, canonical_channels(block), block.t0)
        cursor = adv.cursor
        pending.append(AdmittedBlock(block.seq, cursor.segment, cursor.origin_t0, adv.channels, adv.windows_after, 0))
        if adv.windows_added:
            job = SessionJob(estimator, pending, visual, adv.windows_added, checks)
            pending = []
            (result,) = estimate_batch(runtime, [job])
            if result.error is not None:
                raise result.error
            windows += result.estimates
    cpu = time.process_time() - started
    wall = time.perf_counter() - wall
    full_name = runtime.main.name
    escalated = sum(1 for w in windows if w.model == full_name) if runtime.cheap is not None else len(windows)
    stream_s = len(stream.textures) * stream.seconds
    mid = np.array([0.5 * (w.t_start_s + w.t_end_s) for w in windows])
    texture_of = np.minimum((mid // stream.seconds).astype(int), len(stream.textures) - 1)
    ratings = np.array([w.smoothed for w in windows])
    flagged = sum(1 for w in windows if w.assessment.out_of_distribution)
    print(
        f"{name}: {cpu:.1f} s CPU ({cpu / stream_s * 1e3:.0f} ms per stream second), {embeds} embeddings, "
        f"{len(windows)} windows, {escalated} by the full model, {flagged} flagged",
        flush=True,
    )
    return {
        "policy": name,
        "cpu_s": round(cpu, 3),
        "wall_s": round(wall, 3),
        "cpu_ms_per_stream_s": round(cpu / stream_s * 1e3, 2),
        "embeddings": embeds,
        "frames": len(frames),
        "windows": len(windows),
        "windows_full_model": escalated,
        "windows_flagged": flagged,
        "chosen": [w.chosen for w in windows],
        "ratings": ratings,
        "texture_of": texture_of,
    }


# ---- comparison ------------------------------------------------------------------------------------
def _window_errors(run: dict, stream: Stream) -> np.ndarray:
    """(n,) per-window MAE on the 0–100 scale against the stroked texture's mean rating."""
    return np.abs(run["ratings"] - stream.truth[run["texture_of"]]).mean(axis=1) / 2


def _compare(full: dict, adaptive: dict, stream: Stream, seed: int) -> dict:
    if full["windows"] != adaptive["windows"]:
        raise RuntimeError(f"the policies saw different windows: {full['windows']} vs {adaptive['windows']}")
    ef, ea = _window_errors(full, stream), _window_errors(adaptive, stream)
    same = np.array(full["chosen"]) == np.array(adaptive["chosen"])
    tex = full["texture_of"]
    per_tex = lambda v: np.array([v[tex == k].mean() for k in range(len(stream.textures))])  # noqa: E731
    f_t, a_t, s_t = per_tex(ef), per_tex(ea), per_tex(same.astype(float))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(f_t), size=(2000, len(f_t)))
    ci = lambda v: [round(float(np.percentile(v[idx].mean(axis=1), q)), 3) for q in (2.5, 97.5)]  # noqa: E731
    correct = lambda run: float(np.mean(np.array(run["chosen"]) == np.array(stream.textures)[tex]))  # noqa: E731
    return {
        "compute_ratio": round(full["cpu_s"] / adaptive["cpu_s"], 2),
        "mae_full": round(float(ef.mean()), 3),
        "mae_adaptive": round(float(ea.mean()), 3),
        "choice_agreement": round(float(same.mean()), 4),
        "ci95": {
            "mae_full": ci(f_t),
            "mae_adaptive": ci(a_t),
            "mae_increase": ci(a_t - f_t),
            "choice_agreement": ci(s_t),
        },
        "choice_correct": {"full": round(correct(full), 4), "adaptive": round(correct(adaptive), 4)},
        **{k: v for k, v in adaptive.items() if k not in ("chosen", "ratings", "texture_of", "policy")},
    }


def _meets(v: dict) -> dict:
    return {
        "compute_ratio": v["compute_ratio"] >= TARGETS["compute_ratio"],
        "mae": v["mae_adaptive"] - v["mae_full"] <= TARGETS["mae_increase"],
        "choice_agreement": v["choice_agreement"] >= TARGETS["choice_agreement"],
    }


def _print(result: dict) -> None:
    f = result["full"]
    print(
        f"\nalways-full: {f['cpu_ms_per_stream_s']:.0f} ms CPU per stream second, {f['embeddings']} embeddings, "
        f"{f['windows']} windows"
    )
    print(
        f"{'policy':<18} {'compute ratio':>13} {'MAE full':>9} {'MAE adaptive':>13} {'same choice':>12} "
        f"{'full-model windows':>19} {'embeddings':>11}"
    )
    for name, v in result["variants"].items():
        print(
            f"{name:<18} {v['compute_ratio']:>12.1f}× {v['mae_full']:>9.2f} {v['mae_adaptive']:>13.2f} "
            f"{100 * v['choice_agreement']:>11.1f}% {v['windows_full_model']:>8}/{v['windows']:<10} "
            f"{v['embeddings']:>11}"
        )
    print(
        f"targets: ≥ {TARGETS['compute_ratio']:g}× less compute, ≤ +{TARGETS['mae_increase']} MAE, "
        f"≥ {100 * TARGETS['choice_agreement']:g} % the same choice; "
        f"headline {result['headline']}: {result['meets_targets']}"
    )


if __name__ == "__main__":
    main()
