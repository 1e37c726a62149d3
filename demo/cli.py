"""`hapticlink demo`: the subcommand, registered through the `hapticlink.commands` entry points."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser(
        "demo",
        help="the whole loop on this machine: service + simulated robot + console",
        description="Builds a synthetic world, trains and exports a model, starts the service and a simulated "
        "robot stroking unseen textures, and prints the operator console URL. Assets are cached in --assets.",
    )
    d.add_argument(
        "--assets",
        type=Path,
        default=Path("artifacts/demo"),
        help="where demo assets are built and cached (default artifacts/demo)",
    )
    d.add_argument("--host", default="127.0.0.1", help="address the demo's service listens on (default 127.0.0.1)")
    d.add_argument("--port", type=int, default=8000, help="its TCP port (default 8000; 0: any free port)")
    d.add_argument(
        "--per-texture",
        type=float,
        default=20.0,
        metavar="S",
        help="seconds the robot strokes each texture (default 20)",
    )
    d.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: until Ctrl-C)")
    d.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    import logging

    from demo.assets import prepared
    from demo.run import demo
    from drivers.source import check_positive
    from service.server import check_port_free

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    for flag, seconds in (("--per-texture", args.per_texture), ("--duration", args.duration)):
        if seconds is not None:
            check_positive(flag, seconds)
    check_port_free(args.host, args.port)  # before minutes of building assets
    assets = prepared(args.assets)
    return demo(assets, host=args.host, port=args.port, per_texture_s=args.per_texture, duration_s=args.duration)
