"""Subcommands of the texture library: library build-synthetic | import-hatt | list | render."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    lib = sub.add_parser("library", help="texture libraries: build, import HaTT, list, render")
    lsub = lib.add_subparsers(dest="library_command", required=True, metavar="ACTION")

    s = lsub.add_parser("build-synthetic", help="a library of synthetic-world textures (the demo's default)")
    s.add_argument("--out", required=True)
    s.add_argument("--n-textures", type=int, default=24)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_build_synthetic)

    h = lsub.add_parser("import-hatt", help="a library of HaTT's rendering models (kept outside the repo: licence)")
    h.add_argument("path", help="the hatt-texnet folder, e.g. ../shared/data/hatt-texnet")
    h.add_argument("--out", required=True)
    h.add_argument("--ratings", help="CSV of predicted ratings (hapticlink predict) for textures without human ratings")
    h.set_defaults(func=_import_hatt)

    ls = lsub.add_parser("list", help="entries of a library")
    ls.add_argument("library", nargs="?", help="the library directory (or --library DIR, as `render` takes it)")
    ls.add_argument("--library", dest="library_flag", metavar="DIR", help=argparse.SUPPRESS)
    ls.set_defaults(func=_list)

    r = lsub.add_parser("render", help="synthesize the vibration the operator side would render (1 kHz)")
    r.add_argument("id")
    r.add_argument("--library", required=True)
    r.add_argument("--speed", type=float, required=True, help="mm/s")
    r.add_argument("--force", type=float, required=True, help="N")
    r.add_argument("--seconds", type=float, default=2.0)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", required=True, help=".wav (float32, 1 kHz), .csv (t_s, accel_m_s2) or .npy")
    r.set_defaults(func=_render)


def _build_synthetic(args: argparse.Namespace) -> int:
    from texture_library.synthetic_library import build_synthetic_library

    lib = build_synthetic_library(args.out, n_textures=args.n_textures, seed=args.seed)
    print(f"wrote library {lib.name!r} with {len(lib.entries)} entries to {args.out}")
    return 0


def _import_hatt(args: argparse.Namespace) -> int:
    from texture_library.hatt_library import import_hatt

    lib, skipped = import_hatt(args.path, args.out, predictions=args.ratings)
    print(f"wrote library with {len(lib.entries)} entries to {args.out}")
    if skipped:
        print(f"left out {len(skipped)} texture(s) without human ratings or predictions: {', '.join(skipped)}")
    return 0


def _list(args: argparse.Namespace) -> int:
    from texture_library.attributes import ATTRIBUTES
    from texture_library.library import Library

    if (args.library is None) == (args.library_flag is None):
        raise ValueError("library list: name the library directory once, as LIBRARY or --library DIR")
    lib = Library.load(args.library or args.library_flag)
    print(f"{'id':24s} {'group':12s} " + " ".join(f"{a:>15s}" for a in ATTRIBUTES) + "  source")
    for e in lib.entries:
        print(f"{e.id:24s} {e.group:12s} " + " ".join(f"{v:15.1f}" for v in e.ratings) + f"  {e.ratings_source}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from texture_library.library import Library
    from texture_library.renderer import render_stroke

    if args.seconds <= 0 or args.speed < 0 or args.force < 0:
        raise ValueError("--seconds must be > 0 and --speed, --force ≥ 0")
    if Path(args.out).suffix not in (".wav", ".csv", ".npy"):
        raise ValueError(f"--out must end in .wav, .csv or .npy, got {Path(args.out).name!r}")
    model = Library.load(args.library).model(args.id)
    n = int(round(args.seconds * model.rate_hz))
    excitation = np.random.default_rng(args.seed).standard_normal(n)  # what `synthesis.render` would draw
    accel = render_stroke(model, np.full(n, args.speed), np.full(n, args.force), excitation=excitation)
    out = Path(args.out)
    if out.suffix == ".wav":
        from scipy.io import wavfile

        wavfile.write(out, int(model.rate_hz), accel.astype(np.float32))
    elif out.suffix == ".csv":
        np.savetxt(
            out,
            np.column_stack([np.arange(n) / model.rate_hz, accel]),
            delimiter=",",
            header="t_s,accel_m_s2",
            comments="",
        )
    else:
        np.save(out, accel)
    clipped = args.speed > model.max_speed or args.force > model.max_force
    print(
        f"rendered {n} samples ({args.seconds:g} s at {model.rate_hz:g} Hz), RMS {accel.std():.3f} m/s² → {out}"
        + (f" (clamped to the model's range {model.max_speed:.0f} mm/s, {model.max_force:.1f} N)" if clipped else "")
    )
    return 0
