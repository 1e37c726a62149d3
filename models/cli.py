"""Subcommands of the models part: dataset, features, evaluate, train, predict, report."""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    ds = sub.add_parser("dataset", help="build and check datasets")
    dsub = ds.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")

    b = dsub.add_parser("build", help="build a dataset directory from a source")
    b.add_argument("--source", required=True, choices=["hatt-texnet", "synthetic", "recordings"])
    b.add_argument("--out", required=True, help="dataset directory to write")
    b.add_argument("--path", help="source folder (hatt-texnet, recordings)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--duration", type=float, help="seconds per rendered recording (hatt-texnet 60, synthetic 10)")
    b.add_argument("--recordings", type=int, default=1, help="recordings per texture (rendered sources)")
    b.add_argument("--n-textures", type=int, default=24, help="synthetic: number of textures")
    b.add_argument("--withheld", type=int, default=0, help="synthetic: build the last N textures without ratings")
    b.add_argument("--limit", type=int, help="hatt-texnet: only the first N textures (quick trials)")
    b.add_argument("--rating-scale", default="bipolar", choices=["bipolar", "0-100"], help="recordings: scale of ratings.csv")
    b.add_argument("--no-features", action="store_true", help="skip computing the feature caches")
    b.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    b.set_defaults(func=_dataset_build)

    c = dsub.add_parser("check", help="validate a dataset directory; exit 1 on any problem")
    c.add_argument("dir")
    c.add_argument("--quick", action="store_true", help="structure only: skip decoding recordings and images")
    c.set_defaults(func=_dataset_check)


def _dataset_build(args: argparse.Namespace) -> int:
    import time

    from models.datasets.build import build

    options: dict = {}
    if args.source in ("hatt-texnet", "synthetic"):
        options.update(seed=args.seed, recordings=args.recordings)
        if args.duration is not None:
            options["duration_s"] = args.duration
    if args.source == "hatt-texnet":
        options.update(limit=args.limit, workers=args.workers)
    if args.source == "synthetic":
        options.update(n_textures=args.n_textures, withheld=args.withheld)
    if args.source == "recordings":
        options["rating_scale"] = args.rating_scale
    t0 = time.perf_counter()
    out = build(args.source, args.out, path=args.path, **options)
    print(f"built {args.source} dataset in {out} ({time.perf_counter() - t0:.1f} s)")
    if not args.no_features:
        from models.featurize import featurize_dataset

        t1 = time.perf_counter()
        summary = featurize_dataset(out, workers=args.workers)
        print(f"features cached in {time.perf_counter() - t1:.1f} s: {summary}")
    return 0


def _dataset_check(args: argparse.Namespace) -> int:
    from models.datasets.check import check_dataset

    problems = check_dataset(args.dir, deep=not args.quick)
    for p in problems:
        print(p, file=sys.stderr)
    if problems:
        print(f"{args.dir}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    print(f"{args.dir}: ok")
    return 0
