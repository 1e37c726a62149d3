"""`hapticlink tradeoffs …`: the trade-off studies (frontier, robustness, intervals) and their report."""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from pathlib import Path

from models.offline.tradeoffs import DEFAULT_REPORT, DEFAULT_WORK


def register(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("tradeoffs", help="speed–accuracy frontier, robustness curves, interval coverage, their report")
    tsub = t.add_subparsers(dest="tradeoffs_command", required=True, metavar="STUDY")

    f = tsub.add_parser("frontier", help="accuracy against per-frame and per-window cost over visual configurations")
    f.add_argument("--dataset", required=True)
    f.add_argument("--model", default="ridge-both", help="reference model (default ridge-both)")
    f.add_argument("--seeds", type=int, nargs="+", default=[0])
    f.add_argument("--grids", type=int, nargs="+", default=[7, 5, 3, 2, 1])
    f.add_argument(
        "--resizes",
        nargs="+",
        default=["native", "640", "448"],
        help="shorter side in pixels, or 'native' (1×1 @ 224 is always added)",
    )
    f.add_argument("--backbones", nargs="+", default=["efficientnet_lite0", "resnet50"])
    f.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="onnxruntime intra-op threads to time")
    f.add_argument(
        "--glcm", default="both", choices=["both", "on", "off"], help="configurations with GLCM, without, or both"
    )
    f.add_argument(
        "--descriptor-sets",
        nargs="+",
        default=["none"],
        metavar="SET",
        help="classic descriptor sets beside the backbone, each a comma-separated list or 'none', "
        "e.g. none spectrum,grids (default: none)",
    )
    f.add_argument("--repeats", type=int, default=5, help="timed frames per configuration (interleaved)")
    f.add_argument(
        "--nested-folds",
        type=int,
        default=5,
        help="inner folds of the pick rule: the pick on inner CV over every rated texture, and the rule run "
        "inside every outer fold for its MAE (0: the table alone, no pick)",
    )
    f.add_argument("--workers", type=int, default=1, help="parallel LOOCV folds (1: in this process)")
    f.add_argument("--out", default=None, help=f"JSON (default {DEFAULT_REPORT}/frontier-<model>.json)")
    f.add_argument("--work", default=str(DEFAULT_WORK), help="where the timing run is kept for reuse")
    f.add_argument("--retime", action="store_true", help="time again even if a matching timing run is kept")
    _net_options(f)
    f.set_defaults(func=_frontier)

    a = tsub.add_parser("faults", help="compute (and cache) every texture's faulted touch and camera inputs")
    a.add_argument("--dataset", required=True)
    a.add_argument("--work", default=str(DEFAULT_WORK), help=f"cache folder (default {DEFAULT_WORK}, git-ignored)")
    a.add_argument("--workers", type=int, default=2)
    a.add_argument("--no-visual", action="store_true", help="touch faults only")
    a.set_defaults(func=_faults)

    r = tsub.add_parser("robustness", help="fault curves, breaking points, spread, shift, interval coverage")
    r.add_argument("--dataset", required=True)
    r.add_argument(
        "--runs",
        nargs="+",
        default=list(DEFAULT_RUNS),
        help="model:seeds[:cal+aug+sub] — cal: interval calibration fits, aug: augmented twins, sub: LOOCV "
        f"folds of --subset held-out textures only (default: {' '.join(DEFAULT_RUNS)})",
    )
    r.add_argument("--subset", type=int, default=20, help="held-out textures of the runs flagged 'sub' (fixed, seeded)")
    r.add_argument("--served", default="selected", help="the served model's registry name (named in the report)")
    r.add_argument("--work", default=str(DEFAULT_WORK), help=f"per-texture intermediates (default {DEFAULT_WORK})")
    r.add_argument("--workers", type=int, default=2)
    r.add_argument("--out", default=str(DEFAULT_REPORT / "robustness.json"))
    _net_options(r)
    r.set_defaults(func=_robustness)

    p = tsub.add_parser(
        "report", help="reports/tradeoffs/README.md, its charts and results.json from the studies' JSON"
    )
    p.add_argument(
        "--reports", default=str(DEFAULT_REPORT), help=f"folder of the studies' JSON (default {DEFAULT_REPORT})"
    )
    p.set_defaults(func=_report)


DEFAULT_RUNS = (
    "mean:0",
    "ridge-both:0:cal+aug",
    "knn-both:0:cal",
    "svr-both:0:cal",
    "ann:0:cal+aug",
    "ann:1,2",
    "ann-ensemble:0",
    "selected:0:cal",
    "vtnet-compact:0",
)  # the full grid: hours on 2 cores


def _one_blas_thread(command: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """The command with BLAS/OpenMP capped at one thread: the studies run many small fits on a shared machine."""

    @functools.wraps(command)
    def capped(args: argparse.Namespace) -> int:
        from models.offline.jobs import capped_threads

        with capped_threads(1):
            return command(args)

    return capped


def parse_runs(specs: list[str]) -> list[tuple[str, list[int], bool, bool, bool]]:
    """ "model:seeds[:cal+aug+sub]" → (model, seeds, calibration on the first seed, augmentation on the first
    seed, LOOCV on the held-out subset only)."""
    out = []
    for spec in specs:
        parts = spec.split(":")
        if len(parts) not in (2, 3) or not parts[0]:
            raise ValueError(f"run {spec!r}: expected model:seeds[:cal+aug+sub], e.g. ann:0,1,2:cal")
        try:
            seeds = [int(s) for s in parts[1].split(",")]
        except ValueError:
            raise ValueError(f"run {spec!r}: seeds must be comma-separated integers") from None
        flags = set(parts[2].split("+")) if len(parts) == 3 else set()
        if flags - {"cal", "aug", "sub"}:
            raise ValueError(f"run {spec!r}: unknown flags {sorted(flags - {'cal', 'aug', 'sub'})} (cal, aug, sub)")
        if {"cal", "sub"} <= flags:
            raise ValueError(f"run {spec!r}: interval calibration needs every LOOCV fold; drop 'sub' or 'cal'")
        out.append((parts[0], seeds, "cal" in flags, "aug" in flags, "sub" in flags))
    return out


@_one_blas_thread
def _robustness(args: argparse.Namespace) -> int:
    from models.offline.host import host
    from models.offline.provenance import dataset_inputs, provenance
    from models.offline.tradeoffs.common import write_json
    from models.offline.tradeoffs.robustness import held_out_subset, run_model, study_inputs, summarise

    plan = parse_runs(args.runs)
    work = Path(args.work)
    data, inputs, part, tables = study_inputs(args.dataset, work, workers=args.workers)
    subset = held_out_subset(len(data), args.subset)
    runs: dict[str, list] = {}
    for model, seeds, cal, aug, sub in plan:
        for k, seed in enumerate(seeds):
            runs.setdefault(model, []).append(
                run_model(
                    data,
                    inputs,
                    part,
                    work,
                    model,
                    seed,
                    options=_options(args) if model.startswith(("ann", "vtnet")) else {},
                    calibration=cal and k == 0,
                    augmentation=aug and k == 0,
                    workers=args.workers,
                    held_out=subset if sub else None,
                )
            )
    summary = summarise(data, runs, tables, part)
    out = Path(args.out)
    write_json(
        out,
        {
            **summary,
            "runs": args.runs,
            "subset": args.subset,
            "net_options": _options(args),
            "served": args.served,
            "command": _command(args),
            "host": host(),
            "provenance": provenance(dataset_inputs(args.dataset), _command(args)),
        },
    )
    print(f"wrote {out}")
    return 0


def _report(args: argparse.Namespace) -> int:
    from models.offline.tradeoffs.report import build_tradeoffs_report

    print(f"wrote {build_tradeoffs_report(args.reports)}")
    return 0


@_one_blas_thread
def _faults(args: argparse.Namespace) -> int:
    from models.offline.evaluation.data import load_texture_data
    from models.offline.tradeoffs.faulted import faulted_inputs

    textures = load_texture_data(args.dataset, visual=False).textures
    inputs = faulted_inputs(args.dataset, textures, Path(args.work), visual=not args.no_visual, workers=args.workers)
    n_t = len(inputs.tactile)
    print(
        f"faulted inputs of {len(textures)} textures: {n_t} touch variants"
        + ("" if inputs.visual is None else f", {inputs.visual.shape[1]} camera variants")
        + f" (cached in {args.work})"
    )
    return 0


def _net_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--max-epochs", type=int, help="networks: cap on epochs")
    parser.add_argument(
        "--windows-per-texture", type=int, help="networks: tactile windows drawn per texture each epoch"
    )


def _options(args: argparse.Namespace) -> dict:
    return {k: getattr(args, k) for k in ("max_epochs", "windows_per_texture") if getattr(args, k, None) is not None}


@_one_blas_thread
def _frontier(args: argparse.Namespace) -> int:
    from models.offline.host import host
    from models.offline.provenance import dataset_inputs, provenance
    from models.offline.tradeoffs.common import write_json
    from models.offline.tradeoffs.frontier import run_frontier

    resizes = tuple(None if r == "native" else int(r) for r in args.resizes)
    result = run_frontier(
        args.dataset,
        model=args.model,
        options=_options(args),
        seeds=tuple(args.seeds),
        grids=tuple(args.grids),
        resizes=resizes,
        backbones=tuple(args.backbones),
        threads=tuple(args.threads),
        repeats=args.repeats,
        nested_folds=args.nested_folds,
        workers=args.workers,
        backend="serial" if args.workers == 1 else "process",
        timing_cache=Path(args.work),
        retime=args.retime,
        glcm={"both": (True, False), "on": (True,), "off": (False,)}[args.glcm],
        descriptor_sets=tuple(descriptor_set(s) for s in args.descriptor_sets),
    )
    out = Path(args.out or DEFAULT_REPORT / f"frontier-{args.model}.json")
    write_json(
        out,
        {
            **result,
            "command": _command(args),
            "host": host(),
            "provenance": provenance(dataset_inputs(args.dataset), _command(args)),
        },
    )
    rec = result["recommendation"]
    if rec:
        print(
            f"recommended (the rule on {rec['chosen_by']}): {rec['config']} — inner-CV MAE "
            f"{rec['pick_inner_mae']:.2f} (best {rec['best_config']} {rec['best_mae']:.2f}); the procedure, nested: "
            f"MAE {rec['mae']:.2f} [{rec['mae_ci']['lo']:.2f}, {rec['mae_ci']['hi']:.2f}]; "
            f"{rec['frame_ms_1thread']:.0f} ms per frame (1 thread), "
            f"target {'met' if rec['target_met'] else 'NOT met'} on this run's milliseconds "
            f"(the report also judges it on the quiet-equivalent cost)"
        )
    else:
        print("no pick: --nested-folds 0 scores the table alone")
    print(f"wrote {out}")
    return 0


def descriptor_set(text: str) -> tuple[str, ...]:
    """ "none" → (); "spectrum,grids" → ("spectrum", "grids"), each a known descriptor."""
    from models.visual.config import DESCRIPTOR_NAMES

    if text == "none":
        return ()
    names = tuple(n for n in text.split(",") if n)
    unknown = [n for n in names if n not in DESCRIPTOR_NAMES]
    if unknown or not names:
        raise ValueError(
            f"descriptor set {text!r}: expected 'none' or a comma-separated list of {list(DESCRIPTOR_NAMES)}"
        )
    return names


def _command(args: argparse.Namespace) -> str:
    import shlex
    import sys

    return "hapticlink " + " ".join(shlex.quote(a) for a in sys.argv[1:])
