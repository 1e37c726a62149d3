"""`hapticlink fidelity`: score the selection rules leave-one-texture-out and write reports/fidelity."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    f = sub.add_parser(
        "fidelity",
        help="what the operator feels: selection rules scored leave-one-texture-out → README, charts, results.json",
    )
    add_worlds(f)
    f.add_argument("--windows", type=int, default=24, help="windows per stroked texture for per-window rules")
    f.add_argument("--default-rule", default="hybrid", help="the rule the service serves (marked in the report)")
    f.add_argument("--out", default="reports/fidelity")
    f.set_defaults(func=_fidelity)
    register_online(sub)


def _fidelity(args: argparse.Namespace) -> int:
    from models.offline.fidelity.report import write_report
    from models.offline.fidelity.study import RULE_ORDER, load_world, run_rules, summarise
    from models.offline.provenance import dataset_inputs, file_input, provenance

    # ValueError: `hapticlink` says it as every command does ("hapticlink fidelity: error: …", exit 2)
    if args.default_rule not in RULE_ORDER:
        raise ValueError(f"--default-rule must be one of {RULE_ORDER}, got {args.default_rule!r}")
    if (args.synthetic_dataset is None) != (args.synthetic_predictions is None):
        raise ValueError("--synthetic-dataset and --synthetic-predictions go together")
    if args.windows < 1:
        raise ValueError(f"--windows must be ≥ 1, got {args.windows}")
    parts: list = []
    inputs: list = []
    for dataset, predictions in (
        (args.dataset, args.predictions),
        (args.synthetic_dataset, args.synthetic_predictions),
    ):
        if dataset is None:
            parts.append(None)
            continue
        try:
            world = load_world(dataset, predictions, args.windows)
        except KeyError as exc:
            raise ValueError(f"{dataset}: no {exc} in its files") from None
        inputs += [file_input("predictions", predictions), *dataset_inputs(dataset)]
        per_texture, info = run_rules(world)
        rows = summarise(world, per_texture)
        parts.append((world, per_texture, rows, info))
        print(f"{world.name}: {len(world.textures)} textures; hybrid weight for serving {info['served_weight']:g}")
        for r in rows:
            print(
                f"  {r['rule']:<24} rating {r['rating_distance']:6.2f}  spectral {r['spectral_distance_db']:6.2f} dB"
                f"  pooled {r['pooled_spectral_distance_db']:6.2f} dB"
                f"  weighted {r['weighted_spectral_distance_db']:6.2f} dB  |Δμ| {r['mu_difference']:.3f}"
            )
    command = "hapticlink " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    made_from = provenance(inputs, command)
    out = write_report(Path(args.out), command, args.default_rule, parts[0], parts[1], made_from)
    print(f"wrote {out}/README.md and results.json")
    return 0


def add_worlds(f: argparse.ArgumentParser) -> None:
    """The two worlds both studies read: HaTT–TexNet (required) and the synthetic world, each with its predictions."""
    f.add_argument("--dataset", required=True, help="HaTT–TexNet dataset directory (hapticlink dataset build)")
    f.add_argument("--predictions", required=True, help="results.json of the served model's leave-one-texture-out run")
    f.add_argument("--synthetic-dataset", help="synthetic-world dataset directory (strokes with surface bumps)")
    f.add_argument("--synthetic-predictions", help="results.json of a leave-one-texture-out run on it")


def register_online(sub: argparse._SubParsersAction) -> None:
    f = sub.add_parser(
        "fidelity-online",
        help="what the operator holds over time: the surface's own model learnt online, leave-one-texture-out",
    )
    add_worlds(f)
    f.add_argument("--textures", type=int, default=8, help="stroked textures per world (an evenly spaced subsample)")
    f.add_argument("--out", default="reports/fidelity")
    f.set_defaults(func=_fidelity_online)


def _fidelity_online(args: argparse.Namespace) -> int:
    from models.offline.datasets.format import Dataset
    from models.offline.fidelity.online import run_world, write_online
    from models.offline.fidelity.study import load_world
    from models.offline.provenance import dataset_inputs, file_input, provenance
    from texture_library.vibration import VibrationModel

    if args.textures < 2:
        raise ValueError(f"--textures must be ≥ 2, got {args.textures}")
    entries = {}
    inputs: list = []
    for key, dataset, predictions in (
        ("hatt-texnet", args.dataset, args.predictions),
        ("synthetic", args.synthetic_dataset, args.synthetic_predictions),
    ):
        if dataset is None:
            continue
        world = load_world(dataset, predictions)
        inputs += [file_input("predictions", predictions), *dataset_inputs(dataset)]
        ds = Dataset(dataset)
        models = [VibrationModel.load(ds.vibration_model_path(t)) for t in world.textures]
        entries[key] = run_world(world, models, args.textures)
        print(f"{key}: done", flush=True)
    command = "hapticlink " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    out = write_online(Path(args.out), command, entries, provenance(inputs, command))
    print(f"wrote {out}/online.md and results.json's online key")
    return 0
