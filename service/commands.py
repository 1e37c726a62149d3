"""Subcommands of the service part: serve."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the real-time service (HTTP + WebSocket)",
        description="Serve estimation sessions. Settings come from HAPTICLINK_* environment variables "
        "(docs/service.md); these flags override them.",
    )
    p.add_argument("--model", type=Path, metavar="PATH", help="exported model .onnx (HAPTICLINK_MODEL_PATH)")
    p.add_argument("--library", type=Path, metavar="DIR", help="texture library directory (HAPTICLINK_LIBRARY_DIR)")
    p.add_argument(
        "--backbone",
        type=Path,
        metavar="PATH",
        help="visual backbone .onnx, for visual models (HAPTICLINK_BACKBONE_PATH)",
    )
    p.add_argument(
        "--tactile-model",
        type=Path,
        metavar="PATH",
        help="tactile-only fallback model: estimates windows before the first frame is embedded, or of a surface not "
        "tapped, instead of holding them back (HAPTICLINK_TACTILE_MODEL_PATH)",
    )
    p.add_argument(
        "--cheap-model",
        type=Path,
        metavar="PATH",
        help="cheap model the adaptive policy asks first (HAPTICLINK_CHEAP_MODEL_PATH)",
    )
    p.add_argument("--policy", choices=("adaptive", "always-full"), help="serving policy (HAPTICLINK_SERVING_POLICY)")
    p.add_argument("--host", help="address to listen on (HAPTICLINK_HOST, default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (HAPTICLINK_PORT, default 8000)")
    p.add_argument("--broker", choices=("memory", "redis"), help="event fan-out (HAPTICLINK_BROKER)")
    p.add_argument("--redis-url", help="Redis for --broker redis (HAPTICLINK_REDIS_URL)")
    p.add_argument("--instance-id", help="this replica's name (HAPTICLINK_INSTANCE_ID)")
    p.add_argument(
        "--log-level", choices=("critical", "error", "warning", "info", "debug"), help="HAPTICLINK_LOG_LEVEL"
    )
    p.set_defaults(func=_serve)


FLAG_TO_FIELD = {
    "model": "model_path",
    "library": "library_dir",
    "backbone": "backbone_path",
    "tactile_model": "tactile_model_path",
    "cheap_model": "cheap_model_path",
    "policy": "serving_policy",
    "host": "host",
    "port": "port",
    "broker": "broker",
    "redis_url": "redis_url",
    "instance_id": "instance_id",
    "log_level": "log_level",
}


def settings_from_args(args: argparse.Namespace):
    """Settings from the environment with the given flags on top; ValueError names a bad value."""
    from pydantic import ValidationError

    from service.settings import Settings

    overrides = {
        field: getattr(args, flag) for flag, field in FLAG_TO_FIELD.items() if getattr(args, flag, None) is not None
    }
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"invalid settings: {problems}") from None


def _serve(args: argparse.Namespace) -> int:
    from service.app import create_app
    from service.server import serve

    settings = settings_from_args(args)
    for label, path, flag in (
        ("model", settings.model_path, "--model"),
        ("library", settings.library_dir, "--library"),
    ):
        if path is None:
            raise ValueError(f"no {label} configured: pass {flag} or set HAPTICLINK_{FLAG_TO_FIELD[flag[2:]].upper()}")
        if not path.exists():
            raise ValueError(f"{label} not found: {path}")
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # SIGINT/SIGTERM: the sessions end (operators told), then uvicorn stops accepting, lets open requests finish and
    # runs the lifespan shutdown.
    serve(create_app(settings), settings)
    return 0
