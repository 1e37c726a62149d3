"""Subcommands of the offline wing: dataset, features, evaluate, train, predict, report, tradeoffs, fidelity."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    ds = sub.add_parser("dataset", help="build and check datasets")
    dsub = ds.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")

    b = dsub.add_parser("build", help="build a dataset directory from a source")
    b.add_argument(
        "--source", required=True, choices=["hatt-texnet", "hassan2023", "synthetic", "recordings", "rosbag"]
    )
    b.add_argument("--out", required=True, help="dataset directory to write")
    b.add_argument("--path", help="source folder (hatt-texnet, hassan2023, recordings, rosbag)")
    b.add_argument(
        "--topics",
        metavar="YAML",
        help="rosbag: which topics feed which channels (default: the topic map `hapticlink robot --help` shows)",
    )
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--duration", type=float, help="seconds per rendered recording (hatt-texnet 60, synthetic 10)")
    b.add_argument("--recordings", type=int, default=1, help="recordings per texture (rendered sources)")
    b.add_argument("--n-textures", type=int, default=24, help="synthetic: number of textures")
    b.add_argument("--withheld", type=int, default=0, help="synthetic: build the last N textures without ratings")
    b.add_argument("--limit", type=int, help="hatt-texnet, hassan2023: only the first N textures (quick trials)")
    b.add_argument(
        "--rating-scale", default="bipolar", choices=["bipolar", "0-100"], help="recordings: scale of ratings.csv"
    )
    b.add_argument("--no-features", action="store_true", help="skip computing the feature caches")
    b.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    b.set_defaults(func=_dataset_build)

    c = dsub.add_parser("check", help="validate a dataset directory; exit 1 on any problem")
    c.add_argument("dir")
    c.add_argument("--quick", action="store_true", help="structure only: skip decoding recordings and images")
    c.set_defaults(func=_dataset_check)
    register_models(sub)
    register_report(sub)
    from models.offline.tradeoffs.cli import register as register_tradeoffs

    register_tradeoffs(sub)
    from models.offline.fidelity.cli import register as register_fidelity

    register_fidelity(sub)


def _dataset_build(args: argparse.Namespace) -> int:
    import time

    from models.offline.datasets.build import build

    options: dict = {}
    if args.source in ("hatt-texnet", "synthetic"):
        options.update(seed=args.seed, recordings=args.recordings)
        if args.duration is not None:
            options["duration_s"] = args.duration
    if args.source == "hatt-texnet":
        options.update(limit=args.limit, workers=args.workers)
    if args.source == "hassan2023":
        options.update(limit=args.limit)
    if args.source == "synthetic":
        options.update(n_textures=args.n_textures, withheld=args.withheld)
    if args.source in ("recordings", "rosbag"):
        options["rating_scale"] = args.rating_scale
    if args.source == "rosbag":
        options["topics"] = args.topics
    elif args.topics is not None:
        raise ValueError(f"--topics: only --source rosbag reads a topic map, not {args.source!r}")
    t0 = time.perf_counter()
    out = build(args.source, args.out, path=args.path, **options)
    print(f"built {args.source} dataset in {out} ({time.perf_counter() - t0:.1f} s)")
    if not args.no_features:
        from models.offline.featurize import featurize_dataset

        t1 = time.perf_counter()
        summary = featurize_dataset(out, workers=args.workers)
        print(f"features cached in {time.perf_counter() - t1:.1f} s: {summary}")
    return 0


def _dataset_check(args: argparse.Namespace) -> int:
    from models.offline.datasets.check import check_dataset

    problems = check_dataset(args.dir, deep=not args.quick)
    for p in problems:
        print(p, file=sys.stderr)
    if problems:
        print(f"{args.dir}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    print(f"{args.dir}: ok")
    return 0


def register_models(sub: argparse._SubParsersAction) -> None:
    from models.offline.evaluation.families import LEAVE_OUT

    e = sub.add_parser("evaluate", help="leave-one-texture-out evaluation of one model → results.json + figures")
    e.add_argument("--dataset", required=True)
    e.add_argument(
        "--model",
        required=True,
        help="e.g. selected, krr-pooled, ridge-both, knn-visual, svr-tactile-windows, vtnet-compact, "
        "shuffled-ridge-both, selected-image (image-only datasets)",
    )
    e.add_argument("--out", required=True, help="output folder, e.g. reports/hatt-texnet/ridge-both")
    e.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    e.add_argument("--workers", type=int, help="parallel folds (default: one per core)")
    e.add_argument(
        "--backend",
        default="process",
        choices=["process", "serial", "ray"],
        help="where the (seed, fold) jobs run: worker processes (default), in this process, or Ray tasks",
    )
    e.add_argument("--ray-address", help="Ray cluster to run on (default: $RAY_ADDRESS, else a local Ray instance)")
    e.add_argument(
        "--test-views",
        type=int,
        help="the held-out texture shows only its first K image views (a service that pooled K frames); "
        "training is unchanged. K must divide the stored views (8)",
    )
    e.add_argument(
        "--leave-out",
        choices=LEAVE_OUT,
        default="texture",
        help="what each fold keeps out of training: the held-out texture (default), or its whole family too "
        "(textures whose names differ only in a trailing number, e.g. carpet_1 and carpet_3): a new material, "
        "not a new sample of one seen",
    )
    _feature_args(e)
    _visual_args(e)
    _net_args(e)
    e.add_argument("--no-figures", action="store_true")
    e.add_argument(
        "--latency-only",
        action="store_true",
        help="only (re)measure the per-window latency into an existing OUT/results.json",
    )
    e.set_defaults(func=_evaluate)

    t = sub.add_parser("train", help="train on every rated texture and export ONNX")
    t.add_argument("--dataset", required=True)
    t.add_argument("--model", required=True)
    t.add_argument("--out", required=True, help="model file to write (.onnx)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--metrics", help="results.json of this model's LOOCV, recorded in the model file")
    t.add_argument(
        "--calibration-folds",
        type=int,
        default=10,
        help="K-fold CV that calibrates the card's prediction intervals and OOD detector (0: none)",
    )
    t.add_argument(
        "--interval-scale",
        default="none",
        choices=["none", "distance"],
        help="intervals of constant width, or scaled by feature-space distance (reports/tradeoffs)",
    )
    _feature_args(t)
    _visual_args(t)
    _net_args(t)
    t.set_defaults(func=_train)

    p = sub.add_parser("predict", help="predict every texture of a dataset with an exported model → CSV")
    p.add_argument("--model", required=True, help="model file (.onnx)")
    p.add_argument("--dataset", required=True)
    p.add_argument(
        "--out", required=True, help="CSV: texture, rough_smooth, flat_bumpy, sticky_slippery, hard_soft (bipolar)"
    )
    p.add_argument(
        "--textures", default="all", choices=["all", "yes", "withheld", "no"], help="which textures by rated status"
    )
    p.set_defaults(func=_predict)


def _feature_args(parser: argparse.ArgumentParser) -> None:
    from models.tactile.config import EXTRA_GROUPS

    parser.add_argument("--tactile-features", default="mfcc", choices=["mfcc", "dwt", "dft"])
    parser.add_argument(
        "--extra-groups",
        nargs="*",
        default=[],
        choices=list(EXTRA_GROUPS),
        metavar="GROUP",
        help=f"tactile feature groups added to the feature set: any of {', '.join(EXTRA_GROUPS)} "
        "(friction needs 3-column force; taps needs tap transients per texture)",
    )
    parser.add_argument(
        "--visual-part",
        default="both",
        choices=["both", "backbone", "glcm", "descriptors", "classic"],
        help="visual columns the model reads: both = all; classic = GLCM + descriptors",
    )
    parser.add_argument(
        "--views",
        type=int,
        help="image views pooled per texture (ridge-*, *-pooled, selected; default: ridge 1, pooled models all stored)",
    )


def _visual_args(parser: argparse.ArgumentParser) -> None:
    from typing import get_args

    from models.visual.config import DESCRIPTOR_NAMES, BackboneChoice, BackboneLayer

    parser.add_argument("--visual-grid", type=int, help="patches per side of the backbone grid (default 7)")
    parser.add_argument(
        "--backbone",
        choices=list(get_args(BackboneChoice)),
        help="the image backbone (default auto: ResNet-50 if its weights are found, else EfficientNet-Lite0; "
        "efficientnet_lite0_int8: its int8 copy, the served one)",
    )
    parser.add_argument(
        "--no-glcm", action="store_true", help="compute no GLCM: the frame costs the backbone (and descriptors) alone"
    )
    parser.add_argument(
        "--backbone-layer",
        choices=list(get_args(BackboneLayer)),
        help="where the backbone is read (default head; last_block: EfficientNet-Lite0's last block, mean ⊕ std)",
    )
    parser.add_argument(
        "--descriptors",
        nargs="*",
        default=[],
        choices=list(DESCRIPTOR_NAMES),
        metavar="NAME",
        help=f"classic texture descriptors appended to the visual vector: any of {', '.join(DESCRIPTOR_NAMES)}",
    )


def _visual_config(args: argparse.Namespace):
    from pydantic import ValidationError

    from models.visual.config import VisualConfig
    from texture_library.named_errors import named_errors

    fields: dict = {"descriptors": tuple(getattr(args, "descriptors", None) or ())}
    if getattr(args, "visual_grid", None) is not None:
        fields["grid"] = args.visual_grid
    if getattr(args, "no_glcm", False):
        fields["glcm"] = False
    if getattr(args, "backbone_layer", None) is not None:
        fields["backbone_layer"] = args.backbone_layer
    if getattr(args, "backbone", None) is not None:
        fields["backbone"] = args.backbone
    try:
        return VisualConfig(**fields)
    except ValidationError as exc:  # pydantic's own text names the field, not the flag that set it
        flags = {"grid": "--visual-grid", "backbone_layer": "--backbone-layer", "descriptors": "--descriptors"}
        raise ValueError(
            named_errors(exc, lambda field: flags.get(field, "--" + field.replace("_", "-")), "visual")
        ) from None


def _tactile_config(args: argparse.Namespace):
    from models.tactile.config import TactileConfig

    return TactileConfig(feature_set=args.tactile_features, extra_groups=tuple(args.extra_groups))


def _net_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--max-epochs", type=int, help="networks: cap on epochs (default 200)")
    parser.add_argument(
        "--windows-per-texture", type=int, help="networks: tactile windows drawn per texture each epoch (default 16)"
    )


def _options(args: argparse.Namespace) -> dict:
    """Estimator options given on the command line (networks only; the rest keep their defaults)."""
    names = ("max_epochs", "windows_per_texture", "views")
    return {k: getattr(args, k) for k in names if getattr(args, k, None) is not None}


def _evaluate(args: argparse.Namespace) -> int:
    from models.offline.datasets.format import Dataset
    from models.offline.evaluation.data import load_texture_data
    from models.offline.evaluation.estimator_registry import EstimatorSpec, for_dataset
    from models.offline.evaluation.evaluate import evaluate
    from models.offline.provenance import dataset_inputs

    ds = Dataset(args.dataset)
    # an image-only dataset: a model that needs touch is refused here, naming the model and the missing modality
    spec = for_dataset(EstimatorSpec(args.model, _options(args)), not ds.has_recordings, f"dataset {ds.name!r}")
    modality = spec.build().modality
    _check_test_views(args.test_views, spec.name, modality)
    data = load_texture_data(
        args.dataset,
        tactile_config=_tactile_config(args),
        visual=modality in ("visual", "both"),
        visual_part=args.visual_part,
        workers=args.workers,
        visual_config=_visual_config(args),
    )
    if args.latency_only:
        import json

        from models.offline.evaluation.evaluate import window_latency

        path = Path(args.out) / "results.json"
        if not path.is_file():
            raise ValueError(f"--latency-only needs an existing {path}")
        res = json.loads(path.read_text())
        if res["model"] != args.model:
            raise ValueError(f"{path} holds results of {res['model']!r}, not {args.model!r}")
        res["latency_us"] = window_latency(data, spec)
        path.write_text(json.dumps(res, indent=1))
        latency = res["latency_us"]
        print(f"{args.model}: per-window latency p50 {latency['p50_us']:.0f} µs ({latency['runtime']})")
        return 0
    res = evaluate(
        data,
        spec,
        args.out,
        seeds=tuple(args.seeds),
        workers=args.workers,
        backend=args.backend,
        ray_address=args.ray_address,
        test_views=args.test_views,
        leave_out=args.leave_out,
        inputs=dataset_inputs(args.dataset),
    )
    if not args.no_figures:
        from models.offline.report.evaluation_figures import results_figures

        results_figures(res, data.textures, data.targets, Path(args.out))
    mae, sd = res["mae"], res["mae_std"]
    print(f"{args.model} on {res['dataset']} ({res['n_textures']} textures, seeds {res['seeds']}), MAE 0–100:")
    for k in mae:
        print(f"  {k:16s} {mae[k]:6.2f} ± {sd[k]:.2f}")
    print(f"results in {args.out}/results.json ({res['wall_s']:.0f} s)")
    return 0


def _check_test_views(views: int | None, model: str, modality: str) -> None:
    """Refuse a bad --test-views before any feature is computed (on HaTT that takes ≈ 30 s)."""
    if views is None:
        return
    from models.offline.evaluation.loocv import check_test_views
    from models.offline.featurize import DEFAULT_VIEWS

    if modality not in ("visual", "both"):
        raise ValueError(f"--test-views: model {model!r} reads no images: it has no views to hold out")
    try:
        check_test_views(views, DEFAULT_VIEWS)  # load_texture_data stores DEFAULT_VIEWS views of each image
    except ValueError as exc:
        raise ValueError(f"--test-views: {exc}") from None


def _train(args: argparse.Namespace) -> int:
    from models.inference.predictor import Predictor
    from models.offline.featurize import backbone_onnx
    from models.offline.train import train_and_export
    from models.visual.onnx_backbone import OnnxBackbone

    path = train_and_export(
        args.dataset,
        args.model,
        args.out,
        seed=args.seed,
        tactile_config=_tactile_config(args),
        visual_config=_visual_config(args),
        visual_part=args.visual_part,
        metrics=args.metrics,
        options=_options(args),
        calibration_folds=args.calibration_folds,
        interval_scale=args.interval_scale,
    )
    print(f"wrote {path}")
    predictor = Predictor(path)
    if predictor.needs_visual:  # the backbone exported for the model's own visual configuration
        backbone = backbone_onnx(predictor.visual_config)
        print(f"serve it with --backbone {backbone}")
        source = OnnxBackbone(backbone, min_probe_cosine=None).source_file
        if source:  # a quantized copy: its fp32 source is served where the copy fails its load-time check
            print(f"  (keep {backbone.parent / source} beside it: the fp32 fallback where int8 does not hold)")
    return 0


def _predict(args: argparse.Namespace) -> int:
    from models.offline.train import predict_dataset, write_predictions

    textures, preds = predict_dataset(args.model, args.dataset, rated=None if args.textures == "all" else args.textures)
    write_predictions(args.out, textures, preds)
    print(f"wrote {len(textures)} predictions to {args.out}")
    return 0


def register_report(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser(
        "report", help="one markdown page of every evaluation of a dataset (reports/<dataset>/README.md)"
    )
    r.add_argument(
        "--dataset", required=True, help="the dataset the results were computed on (for the human noise ceiling)"
    )
    r.add_argument(
        "--reports", required=True, help="folder holding <model>/results.json (and ablation/<run>/results.json)"
    )
    r.add_argument("--regenerate", default="", help="the command that regenerates the page, quoted on it")
    r.add_argument(
        "--readme",
        default=None,
        help="also rewrite the results table of this file (e.g. README.md) between its table markers",
    )
    r.set_defaults(func=_report)


def _report(args: argparse.Namespace) -> int:
    from models.offline.report.markdown import build_report

    print(f"wrote {build_report(args.dataset, args.reports, regenerate=args.regenerate, readme=args.readme)}")
    if args.readme:
        print(f"wrote the results table of {args.readme}")
    return 0
