"""Subcommands of the drivers part: robot (stream a sensor source to the service), operator (render the chosen
textures on the operator's side: drivers/operator/cli.py), and `library add --from-session` (a session's learnt
surface model into a library: it talks HTTP, which the texture library's own commands never do)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from drivers.robot.frames import FRAME_REFRESH_S
from drivers.scene_change import FRAME_CHANGE
from drivers.source import DEFAULT_BLOCK_S, MODEL_RATE_HZ, SLOW_CHANNEL_BLOCK_S

SOURCE_SPECS = (
    "simulated:LIBRARY_DIR:ENTRY_ID",
    "replay:DATASET_DIR:TEXTURE_ID",
    "serial:PORT[:BAUD]",
    "usb:VID:PID",
    "camera-dir:DIR",
    "rosbag:PATH",
)


def register(sub: argparse._SubParsersAction) -> None:
    from drivers.operator.cli import add_parser as add_operator

    _register_robot(sub)
    add_operator(sub)
    _register_library_add(sub)
    _register_record(sub)


def _register_library_add(sub: argparse._SubParsersAction) -> None:
    """`library add` beside the texture library's own actions (registered before this part's)."""
    library = sub.choices.get("library")
    if library is None:
        return
    actions = next(a for a in library._actions if isinstance(a, argparse._SubParsersAction))
    p = actions.add_parser(
        "add",
        help="save a session's learnt surface model into a library, with its provenance",
        description="Save the surface model a session has learnt from its robot's stream (the service's "
        "HAPTICLINK_SURFACE_MODEL) into a library (created when DIR holds none), with where it came from.",
    )
    p.add_argument(
        "--from-session", nargs=2, required=True, metavar=("URL", "SESSION"), help="the service and the session id"
    )
    p.add_argument("--token", required=True, metavar="T", help="the session's operator token")
    p.add_argument("--library", required=True, metavar="DIR")
    p.add_argument("--id", metavar="ID", help="the entry's id (default: session-<session id>)")
    p.add_argument("--name", help="the entry's name (default: the session's name, learnt)")
    p.add_argument("--group", default="learnt", help="the entry's group (default: learnt)")
    p.set_defaults(func=_library_add)


def _library_add(args: argparse.Namespace) -> int:
    from drivers.session_model import fetch_session_model, save_to_library

    url, session_id = args.from_session
    fetched = fetch_session_model(url, session_id, args.token)
    entry = save_to_library(fetched, args.library, url, args.id, args.name, args.group)
    print(f"added {entry.id!r} to {args.library}: {entry.provenance}")
    return 0


def _register_robot(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "robot",
        help="stream a sensor source (simulated, replay, serial, usb, camera-dir, rosbag) to the service",
        description="Stream a sensor source to a hapticlink service, reconnecting and resending across outages.",
        epilog=_rosbag_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--source", required=True, metavar="SPEC", help="one of: " + ", ".join(SOURCE_SPECS))
    p.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    p.add_argument("--session", metavar="ID", help="stream into this session (needs --token); default: create one")
    p.add_argument("--token", metavar="T", help="the session's robot token")
    p.add_argument("--name", help="name of the session to create")
    p.add_argument(
        "--robot-id",
        metavar="ID",
        help="this robot's own id: operators follow the robot by it across its sessions (`hapticlink operator "
        "--robot ID`), a restart of the service included (1–64 letters, digits, '_', '-', '.', ':')",
    )
    p.add_argument(
        "--api-key", metavar="KEY", help="the fleet API key that opens sessions (default: $HAPTICLINK_API_KEY)"
    )
    p.add_argument(
        "--transport", choices=("ws", "http"), default="ws", help="WebSocket (default) or one HTTP POST per block"
    )
    p.add_argument("--json", action="store_true", help="send JSON blocks instead of the binary format")
    p.add_argument(
        "--duration", type=float, metavar="S", help="stop reading after S seconds, deliver what is buffered, exit"
    )
    p.add_argument(
        "--realtime",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="pace simulated/replay sources in real time (default)",
    )
    p.add_argument(
        "--block-s",
        type=float,
        default=None,
        metavar="S",
        help=f"seconds per block (default {DEFAULT_BLOCK_S:g}: {0.5 / DEFAULT_BLOCK_S:.0f} blocks per 500 ms window; "
        f"{SLOW_CHANNEL_BLOCK_S:g} when a channel runs below {MODEL_RATE_HZ / 1000:g} kHz; the service takes blocks of "
        "up to 1 s unless HAPTICLINK_MAX_BLOCK_S says more)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulated: random seed")
    p.add_argument("--image", metavar="FILE", help="simulated: the texture's image, sent as a camera frame")
    p.add_argument(
        "--taps",
        action="store_true",
        help="simulated: tap the surface before stroking it (one tap block of the texture's tap transients)",
    )
    p.add_argument(
        "--recording", type=int, default=0, metavar="N", help="replay: which of the texture's recordings (default 0)"
    )
    p.add_argument("--loop", action="store_true", help="replay: play the recording again and again")
    p.add_argument(
        "--topics",
        metavar="YAML",
        help="rosbag: which topics feed which channels (default: the topic map below; copy it and edit it)",
    )
    p.add_argument(
        "--start-seq",
        type=int,
        default=0,
        metavar="N",
        help="seq of the first block (resuming a session: above its last)",
    )
    p.add_argument(
        "--max-buffer-s",
        type=float,
        default=60.0,
        metavar="S",
        help="seconds of unacknowledged data kept for resending (default 60)",
    )
    p.add_argument(
        "--frame-change",
        type=float,
        default=FRAME_CHANGE,
        metavar="D",
        help=f"send a camera frame only when its scene changed by more than D since the last one sent (default "
        f"{FRAME_CHANGE:g}, the service's own scene-change threshold; 0: send every frame)",
    )
    p.add_argument(
        "--frame-refresh-s",
        type=float,
        default=FRAME_REFRESH_S,
        metavar="S",
        help=f"… or once S seconds, up to a quarter more, drawn anew each time, have passed since it (default "
        f"{FRAME_REFRESH_S:g})",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    p.set_defaults(func=_run_robot)


def _register_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="record a session's estimates as MCAP, on the robot's clock (open it in Foxglove beside the robot's bag)",
        description="Follow a session's event feed and write every event into an MCAP file: JSON channels with JSON "
        "schemas for the ratings and their intervals, the OOD flag, the chosen model and its version, the latency, "
        "and status events, logged at each window's end on the robot's clock (docs/ros2.md).",
    )
    p.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    p.add_argument("--session", required=True, metavar="ID", help="the session to record")
    p.add_argument("--token", required=True, metavar="T", help="the session's operator token")
    p.add_argument("--mcap", metavar="OUT", help="the MCAP file to write (replaced if it exists)")
    p.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help="also publish the same channels live over the Foxglove WebSocket protocol (off by default; host "
        "127.0.0.1 unless given): open ws://HOST:PORT in Foxglove",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="stop after S seconds (default: the session's end, or Ctrl-C; the MCAP file is finished either way)",
    )
    p.set_defaults(func=_run_record)


def _run_record(args: argparse.Namespace) -> int:
    import asyncio
    from pathlib import Path

    from drivers.estimates_mcap import EstimatesMcap, EventSink, SessionRecorder

    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.mcap is None and args.foxglove is None:
        raise ValueError("record: give --mcap OUT, --foxglove [HOST:]PORT, or both")
    sinks: list[EventSink] = []
    if args.foxglove is not None:
        from drivers.estimates_foxglove import FoxgloveLive

        host, _, port = args.foxglove.rpartition(":")
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"--foxglove: expected [HOST:]PORT with a port in 1…65535, got {args.foxglove!r}")
        live = FoxgloveLive(host or "127.0.0.1", int(port))
        print(f"foxglove: open {live.url} in Foxglove (Open connection → Foxglove WebSocket)", flush=True)
        sinks.append(live)
    mcap_file = None if args.mcap is None else Path(args.mcap).open("wb")
    if mcap_file is not None:
        sinks.append(EstimatesMcap(mcap_file))
    recorder = SessionRecorder(args.url, args.session, args.token, sinks)
    try:
        n = asyncio.run(_record(recorder, args.duration))
    except KeyboardInterrupt:  # a Ctrl-C before the loop took the signals over
        n = recorder.events
    finally:
        if mcap_file is not None:
            mcap_file.close()
    print(f"recorded {n} event(s)" + (f" into {args.mcap}" if args.mcap else ""))
    return 0


async def _record(recorder, duration_s: float | None) -> int:
    """Record until the session ends, duration_s passes, or Ctrl-C (or SIGTERM): the first stops the recorder as the
    session's end does (the MCAP file finished, the Foxglove server stopped); a second quits at once."""
    import os

    from drivers.stop_signals import on_stop_signals

    interrupted = False

    def on_signal() -> None:
        nonlocal interrupted
        if interrupted:
            print("hapticlink record: quitting now", file=sys.stderr, flush=True)
            os._exit(130)
        interrupted = True
        print("stopping: finishing the recording (Ctrl-C again to quit now)", file=sys.stderr, flush=True)
        recorder.stop()

    with on_stop_signals(on_signal):
        return await recorder.run(duration_s)


def _rosbag_epilog() -> str:
    from drivers.rosbag_mapping import default_topics_text

    return (
        "rosbag:PATH reads a ROS 2 bag (a bag folder, .db3 or .mcap) recorded by your robot, paced at its own "
        "stamps.\nIts default topic map (--topics YAML to change it):\n\n" + default_topics_text()
    )


def _split_dir_id(kind: str, rest: str, what: str) -> tuple[Path, str]:
    # rsplit: the directory may itself contain ':' (Windows drive letters); ids never do.
    if ":" not in rest:
        raise ValueError(f"source {kind}: expected {kind}:DIR:{what}, got {kind}:{rest!r}")
    directory, ident = rest.rsplit(":", 1)
    if not directory or not ident:
        raise ValueError(f"source {kind}: expected {kind}:DIR:{what} with both parts non-empty, got {kind}:{rest!r}")
    if not Path(directory).is_dir():
        raise ValueError(f"source {kind}: {directory!r} is not a directory")
    return Path(directory), ident


def _parse_usb_id(label: str, text: str) -> int:
    try:
        value = int(text, 16)
    except ValueError:
        raise ValueError(f"source usb: {label} must be hexadecimal (e.g. 1209 or 0x1209), got {text!r}") from None
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"source usb: {label} must lie in 0000…ffff, got {text!r}")
    return value


def source_from_spec(
    spec: str,
    *,
    realtime: bool = True,
    block_s: float | None = None,
    seed: int = 0,
    image: str | None = None,
    recording: int = 0,
    loop: bool = False,
    taps: bool = False,
    topics: str | None = None,
):
    """Build the SensorSource a SPEC names (see SOURCE_SPECS); ValueError says what is wrong with it."""
    kind, sep, rest = spec.partition(":")
    if not sep or not rest:
        raise ValueError(f"source spec {spec!r} must be one of: {', '.join(SOURCE_SPECS)}")
    if taps and kind != "simulated":
        raise ValueError(f"--taps: only the simulated source performs the tap procedure, not {kind!r}")
    if kind == "simulated":
        from drivers.simulated import SimulatedSource

        lib, entry = _split_dir_id(kind, rest, "ENTRY_ID")
        return SimulatedSource.from_library(
            lib, entry, image_path=image, seed=seed, block_s=block_s, realtime=realtime, taps=taps
        )
    if kind == "replay":
        from drivers.replay import ReplaySource

        dataset, texture = _split_dir_id(kind, rest, "TEXTURE_ID")
        return ReplaySource.from_dataset(
            dataset, texture, recording=recording, block_s=block_s, realtime=realtime, loop=loop
        )
    if kind == "serial":
        from drivers.serial_board import SerialBoardSource

        port, baud = rest, None
        head, _, tail = rest.rpartition(":")
        if head and tail.isdigit():
            port, baud = head, int(tail)
        if baud is not None and baud <= 0:
            raise ValueError(f"source serial: baud rate must be positive, got {baud}")
        return (
            SerialBoardSource(port, block_s=block_s)
            if baud is None
            else SerialBoardSource(port, baudrate=baud, block_s=block_s)
        )
    if kind == "usb":
        from drivers.usb_daq import UsbDaqSource

        parts = rest.split(":")
        if len(parts) != 2:
            raise ValueError(f"source usb: expected usb:VID:PID in hexadecimal, got {spec!r}")
        return UsbDaqSource(_parse_usb_id("VID", parts[0]), _parse_usb_id("PID", parts[1]), block_s=block_s)
    if topics is not None and kind != "rosbag":
        raise ValueError(f"--topics: only the rosbag source reads a topic map, not {kind!r}")
    if kind == "rosbag":
        from drivers.rosbag_mapping import load_topic_map
        from drivers.rosbag_source import RosbagSource

        return RosbagSource(rest, load_topic_map(topics), block_s=block_s, realtime=realtime)
    if kind == "camera-dir":
        from drivers.camera import WatchedDirectorySource

        return WatchedDirectorySource(rest)
    raise ValueError(f"unknown source kind {kind!r}; SPEC must be one of: {', '.join(SOURCE_SPECS)}")


def _run_robot(args: argparse.Namespace) -> int:
    import asyncio
    import json
    import logging

    from drivers.robot import RobotClient, ServiceRefused
    from drivers.stop_signals import run_until_stopped

    if (args.session is None) != (args.token is None):
        raise ValueError("--session and --token go together (stream into that session), or give neither (create one)")
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.block_s is not None and not args.block_s > 0:
        raise ValueError(f"--block-s must be a positive number of seconds, got {args.block_s}")
    if args.seed < 0:  # numpy's own refusal names no flag
        raise ValueError(f"--seed must be a whole number ≥ 0, got {args.seed}")
    if not logging.getLogger().handlers:
        logging.basicConfig(
            level=logging.DEBUG if args.verbose else logging.INFO,
            format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        )
        # httpx logs every request at INFO: 50 a second here.
        logging.getLogger("httpx").setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    source = source_from_spec(
        args.source,
        realtime=args.realtime,
        block_s=args.block_s,
        seed=args.seed,
        image=args.image,
        recording=args.recording,
        loop=args.loop,
        taps=args.taps,
        topics=args.topics,
    )
    client = RobotClient(
        args.url,
        source,
        session_id=args.session,
        robot_token=args.token,
        transport=args.transport,
        binary=not args.json,
        max_buffer_s=args.max_buffer_s,
        session_name=args.name,
        start_seq=args.start_seq,
        api_key=args.api_key,
        frame_change=args.frame_change,
        frame_refresh_s=args.frame_refresh_s,
        on_session=_print_session,
        robot_id=args.robot_id,
    )
    try:
        stats = asyncio.run(run_until_stopped(client, args.duration, "delivering buffered blocks"))
    except asyncio.CancelledError:
        return 130
    except (ServiceRefused, OSError, LookupError) as exc:
        # Device missing, port unavailable, token refused: say so without a traceback.
        print(f"hapticlink robot: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(stats.as_dict()))
    return 1 if stats.lost or stats.unsent or stats.rejected else 0


def _print_session(info) -> None:
    """The session the robot opened, once its source gave something: where its operators watch."""
    print(f"session {info.session_id}\noperator token {info.operator_token}\nconsole {info.console_url}", flush=True)
