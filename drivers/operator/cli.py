"""`hapticlink operator`: render a session's chosen textures on the operator's side."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys

DEVICE_SPECS = ("simulated[:SECONDS]", "recorded:FILE", "serial:PORT[:BAUD]")
OUTPUT_SPECS = ("wav:FILE", "sound[:DEVICE]", "serial:PORT[:BAUD]")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "operator",
        help="feel the remote surface: render a session's chosen textures to a sound card, WAV file or device",
        description="Follow a session's render feed, fetch each chosen rendering model once, read the operator's "
        "device (speed and force), render the texture's vibration and write it out. Prints each switch's latency.",
    )
    p.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    p.add_argument("--session", metavar="ID", help="the session to follow (or --robot)")
    p.add_argument(
        "--robot",
        metavar="ID",
        help="follow this robot (its --robot-id) across its sessions, a restart of the service included, with the "
        "fleet API key as --token (default: $HAPTICLINK_API_KEY)",
    )
    p.add_argument("--token", metavar="T", help="the session's operator token, or (--robot) the fleet API key")
    p.add_argument(
        "--device",
        default="simulated",
        metavar="SPEC",
        help="one of: " + ", ".join(DEVICE_SPECS) + " (default: simulated)",
    )
    p.add_argument(
        "--out",
        action="append",
        metavar="SPEC",
        help="one or more of: " + ", ".join(OUTPUT_SPECS) + " (repeatable; default: sound)",
    )
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: the device's end)")
    p.add_argument("--full-scale", type=float, default=40.0, metavar="M_S2", help="m/s² at full scale (default 40)")
    p.add_argument("--crossfade-s", type=float, default=0.05, metavar="S", help="switch crossfade (default 0.05)")
    p.add_argument("--block-s", type=float, default=0.01, metavar="S", help="rendering block (default 0.01 s)")
    p.add_argument(
        "--view", choices=("render", "full"), default="render", help="the lean render feed (default) or every event"
    )
    p.add_argument("--json-models", action="store_true", help="fetch models as JSON instead of the compact encoding")
    p.add_argument(
        "--library",
        metavar="DIR",
        help="a copy of the service's library held in advance (shared beforehand): its entries are named on the "
        "feed, never sent",
    )
    p.add_argument(
        "--fetch-models",
        action="store_true",
        help="fetch each model over HTTP instead of taking them pushed on the feed (only what is lacking; deltas)",
    )
    p.add_argument("--loop", action="store_true", help="recorded: play the recording again and again")
    p.add_argument("--seed", type=int, default=0, help="excitation and simulated-stroke seed")
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    p.set_defaults(func=run)


def device_from_spec(spec: str, *, block_s: float, seed: int, loop: bool):
    """The operator device a SPEC names (DEVICE_SPECS); ValueError says what is wrong with it."""
    from drivers.operator.devices import RecordedStroke, SerialDevice, SimulatedStroke

    kind, _, rest = spec.partition(":")
    if kind == "simulated":
        seconds = float(rest) if rest else 3600.0
        if not seconds > 0:
            raise ValueError(f"device simulated: seconds must be > 0, got {rest!r}")
        return SimulatedStroke(seconds, seed=seed, block_s=block_s)
    if kind == "recorded" and rest:
        return RecordedStroke(rest, block_s=block_s, loop=loop)
    if kind == "serial" and rest:
        port, baud = _port_baud(rest)
        return SerialDevice(port, baud, block_s=block_s)
    raise ValueError(f"device spec {spec!r} must be one of: {', '.join(DEVICE_SPECS)}")


def output_from_spec(spec: str, *, full_scale: float):
    """The output a SPEC names (OUTPUT_SPECS); ValueError/RuntimeError says what is wrong with it."""
    from drivers.operator.outputs import SerialOutput, SoundOutput, WavOutput

    kind, _, rest = spec.partition(":")
    if kind == "wav" and rest:
        return WavOutput(rest, full_scale)
    if kind == "sound":
        device: str | int | None = int(rest) if rest.isdigit() else (rest or None)
        return SoundOutput(device, full_scale)
    if kind == "serial" and rest:
        return SerialOutput(*_port_baud(rest))
    raise ValueError(f"output spec {spec!r} must be one of: {', '.join(OUTPUT_SPECS)}")


def _port_baud(rest: str) -> tuple[str, int]:
    head, _, tail = rest.rpartition(":")
    if head and tail.isdigit():
        if int(tail) <= 0:
            raise ValueError(f"serial: baud rate must be positive, got {tail}")
        return head, int(tail)
    return rest, 921_600


def run(args: argparse.Namespace) -> int:
    from drivers.operator.client import OperatorClient, Switch
    from drivers.protocol import API_KEY_ENV, check_service_url
    from drivers.stop_signals import run_until_stopped

    # checked before anything connects: found later (or never), they cost a session's worth of retries
    check_service_url(args.url)
    if (args.session is None) == (args.robot is None):
        raise ValueError("give --session (with its operator --token) or --robot (with the fleet API key), not both")
    token = args.token if args.token is not None else (os.environ.get(API_KEY_ENV) if args.robot else None)
    if not token:
        raise ValueError(
            "--token is required: the session's operator token"
            + (f", or with --robot the fleet API key (or set {API_KEY_ENV})" if args.robot else "")
        )
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not 0 < args.block_s <= 0.1:
        raise ValueError(f"--block-s must lie in (0, 0.1] s (a rendering block; 0.01 by default), got {args.block_s}")
    if not 0 <= args.crossfade_s <= 1:
        raise ValueError(f"--crossfade-s must lie in [0, 1] s, got {args.crossfade_s}")
    if not args.full_scale > 0:
        raise ValueError(f"--full-scale must be a positive acceleration, m/s², got {args.full_scale}")
    if not logging.getLogger().handlers:
        logging.basicConfig(
            level=logging.DEBUG if args.verbose else logging.INFO,
            format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        )
        logging.getLogger("httpx").setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    device = device_from_spec(args.device, block_s=args.block_s, seed=args.seed, loop=args.loop)
    outputs, failed = [], []
    for spec in args.out or ["sound"]:
        try:
            outputs.append(output_from_spec(spec, full_scale=args.full_scale))
        except (RuntimeError, OSError) as exc:  # no sound card or PortAudio, a serial port that does not open
            failed.append(str(exc) if str(exc).startswith(spec.partition(":")[0]) else f"{spec}: {exc}")
    for why in failed:
        print(f"hapticlink operator: {why}", file=sys.stderr)
    if not outputs:
        return 2
    if failed:  # a headless machine asked for sound beside a WAV file: render into what did open
        print(f"hapticlink operator: rendering to {', '.join(o.name for o in outputs)} only", file=sys.stderr)

    library = None
    if args.library:
        from texture_library.library import Library  # noqa: PLC0415 - only with --library

        try:
            library = Library.load(args.library)
        except (OSError, ValueError) as exc:
            print(f"hapticlink operator: --library {args.library}: {exc}", file=sys.stderr)
            for out in outputs:
                out.close()
            return 2

    def said(s: Switch) -> None:
        fetched = f", model fetched in {s.fetch_ms:.1f} ms" if s.fetch_ms else ", model at hand (held or pushed)"
        print(
            f"now rendering {s.entry} ({s.version}): {s.latency_ms:.1f} ms after its window event{fetched}", flush=True
        )

    client = OperatorClient(
        args.url,
        args.session,
        token,
        device,
        outputs,
        view=args.view,
        compact=not args.json_models,
        crossfade_s=args.crossfade_s,
        block_s=args.block_s,
        seed=args.seed,
        on_switch=said,
        robot=args.robot,
        push=not args.fetch_models,
        library=library,
    )
    try:
        stats = asyncio.run(run_until_stopped(client, args.duration, "finishing the output"))
    except (KeyboardInterrupt, asyncio.CancelledError):  # a Ctrl-C before the loop took the signals over, or a second
        return 130
    finally:
        for out in outputs:
            out.close()
    latencies = [s.latency_ms for s in stats.switches if s.latency_ms is not None]
    print(
        f"rendered {stats.samples / 1000:.1f} s ({stats.silent_samples / 1000:.1f} s silent), "
        f"{len(stats.switches)} switch(es)"
        + (f", latency median {sorted(latencies)[len(latencies) // 2]:.1f} ms" if latencies else "")
        + f", {len(stats.model_errors)} model error(s), {stats.stalls} device stall(s)"
        + (f"; {stats.ended}" if stats.ended else "")
        + ("; never reached the service's event feed" if not stats.connects and not stats.refused else ""),
        flush=True,
    )
    return 1 if stats.refused or not stats.connects else 0
