"""`hapticlink tradeoffs …`: the studies of issue 7 and their report."""

from __future__ import annotations

import argparse
from pathlib import Path

from models.tradeoffs.common import DEFAULT_REPORT, DEFAULT_WORK


def register(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("tradeoffs", help="speed–accuracy frontier, robustness curves, interval coverage, their report")
    tsub = t.add_subparsers(dest="tradeoffs_command", required=True, metavar="STUDY")

    f = tsub.add_parser("frontier", help="accuracy against per-frame and per-window cost over visual configurations")
    f.add_argument("--dataset", required=True)
    f.add_argument("--model", default="ridge-both", help="reference model (default ridge-both)")
    f.add_argument("--seeds", type=int, nargs="+", default=[0])
    f.add_argument("--grids", type=int, nargs="+", default=[7, 5, 3, 2, 1])
    f.add_argument("--resizes", nargs="+", default=["native", "640", "448"],
                   help="shorter side in pixels, or 'native' (1×1 @ 224 is always added)")
    f.add_argument("--backbones", nargs="+", default=["efficientnet_lite0", "resnet50"])
    f.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="onnxruntime intra-op threads to time")
    f.add_argument("--repeats", type=int, default=5, help="timed frames per configuration (interleaved)")
    f.add_argument("--nested-folds", type=int, default=5, help="inner folds of the nested check of the pick rule (0: skip)")
    f.add_argument("--workers", type=int, default=1, help="parallel LOOCV folds (1: in this process)")
    f.add_argument("--out", default=None, help=f"JSON (default {DEFAULT_REPORT}/frontier-<model>.json)")
    _net_options(f)
    f.set_defaults(func=_frontier)

    a = tsub.add_parser("faults", help="compute (and cache) every texture's faulted touch and camera inputs")
    a.add_argument("--dataset", required=True)
    a.add_argument("--work", default=str(DEFAULT_WORK), help=f"cache folder (default {DEFAULT_WORK}, git-ignored)")
    a.add_argument("--workers", type=int, default=2)
    a.add_argument("--no-visual", action="store_true", help="touch faults only")
    a.set_defaults(func=_faults)


def _faults(args: argparse.Namespace) -> int:
    from models.evaluation.data import load_texture_data
    from models.tradeoffs.faulted import faulted_inputs

    textures = load_texture_data(args.dataset, visual=False).textures
    inputs = faulted_inputs(args.dataset, textures, Path(args.work), visual=not args.no_visual, workers=args.workers)
    n_t = len(inputs.tactile)
    print(f"faulted inputs of {len(textures)} textures: {n_t} touch variants"
          + ("" if inputs.visual is None else f", {inputs.visual.shape[1]} camera variants") + f" (cached in {args.work})")
    return 0


def _net_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--max-epochs", type=int, help="networks: cap on epochs")
    parser.add_argument("--windows-per-texture", type=int, help="networks: tactile windows drawn per texture each epoch")


def _options(args: argparse.Namespace) -> dict:
    return {k: getattr(args, k) for k in ("max_epochs", "windows_per_texture") if getattr(args, k, None) is not None}


def _frontier(args: argparse.Namespace) -> int:
    from models.tradeoffs.common import write_json
    from models.tradeoffs.frontier import run_frontier

    resizes = tuple(None if r == "native" else int(r) for r in args.resizes)
    result = run_frontier(args.dataset, model=args.model, options=_options(args), seeds=tuple(args.seeds),
                          grids=tuple(args.grids), resizes=resizes, backbones=tuple(args.backbones),
                          threads=tuple(args.threads), repeats=args.repeats, nested_folds=args.nested_folds,
                          workers=args.workers, backend="serial" if args.workers == 1 else "process")
    out = Path(args.out or DEFAULT_REPORT / f"frontier-{args.model}.json")
    write_json(out, {**result, "command": _command(args)})
    rec = result["recommendation"]
    if rec:
        print(f"recommended: {rec['config']} — MAE {rec['mae']:.2f} [{rec['mae_ci']['lo']:.2f}, {rec['mae_ci']['hi']:.2f}], "
              f"{rec['frame_ms_1thread']:.0f} ms per frame (1 thread); best {rec['best_config']} {rec['best_mae']:.2f}; "
              f"target {'met' if rec['target_met'] else 'NOT met'}")
    print(f"wrote {out}")
    return 0


def _command(args: argparse.Namespace) -> str:
    import shlex
    import sys

    return "hapticlink " + " ".join(shlex.quote(a) for a in sys.argv[1:])



