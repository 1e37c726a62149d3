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
    import re

    from pydantic import ValidationError
    from pydantic_settings import SettingsError

    from service.settings import Settings, env_name
    from texture_library.named_errors import named_errors

    overrides = {
        field: getattr(args, flag) for flag, field in FLAG_TO_FIELD.items() if getattr(args, flag, None) is not None
    }
    try:
        return Settings(**overrides)
    except ValidationError as exc:

        def named(field: str) -> str:  # a value comes from a flag or from the environment: name both
            flags = [f"--{flag.replace('_', '-')}" for flag, f in FLAG_TO_FIELD.items() if f == field]
            return f"{flags[0]} ({env_name(field)})" if flags else env_name(field)

        raise ValueError(f"invalid settings: {named_errors(exc, named, 'settings')}") from None
    except SettingsError as exc:  # a list or mapping variable that is not JSON: pydantic names neither it nor why
        field = re.search(r'field "(\w+)"', str(exc))
        name = env_name(field.group(1)) if field else "a HAPTICLINK_ variable"
        raise ValueError(f"{name} must be JSON (a list is written [1, 2]): {exc.__cause__ or exc}") from None


#: the paths `serve` reads: (its flag, what it names, a folder rather than a file, required)
SERVED_PATHS = (
    ("--model", "model", False, True),
    ("--library", "library", True, True),
    ("--backbone", "visual backbone", False, False),
    ("--tactile-model", "tactile fallback model", False, False),
    ("--cheap-model", "cheap model", False, False),
)


def check_paths(settings) -> None:
    """ValueError naming the first path `serve` would read that is missing or of the wrong kind, with its flag and
    variable: checked before anything starts (found later, the service ran on, never ready)."""
    for flag, label, folder, required in SERVED_PATHS:
        field = FLAG_TO_FIELD[flag[2:].replace("-", "_")]
        path, where = getattr(settings, field), f"{flag} or HAPTICLINK_{field.upper()}"
        if path is None:
            if required:
                raise ValueError(f"no {label} configured: pass {where.replace(' or ', ' or set ')}")
        elif not path.exists():
            raise ValueError(f"{label} not found: {path} ({where})")
        elif folder != path.is_dir():
            kind = ("a folder", "the file") if folder else ("a file", "the folder")
            raise ValueError(f"{label} must be {kind[0]}, got {kind[1]} {path} ({where})")


def check_broker(settings, timeout_s: float = 3.0) -> None:
    """ValueError when the Redis that broker=redis names does not answer a PING within timeout_s: said in one line
    before anything starts (found at start-up, it ended the service with a traceback). The URL is said without its
    password."""
    if settings.broker != "redis":
        return
    import redis

    client = redis.Redis.from_url(settings.redis_url, socket_connect_timeout=timeout_s, socket_timeout=timeout_s)
    try:
        client.ping()
    except redis.RedisError as exc:
        raise ValueError(
            f"cannot reach Redis at {redact_password(settings.redis_url)} ({exc}): start redis-server, or pass "
            "--redis-url (HAPTICLINK_REDIS_URL)"
        ) from None
    finally:
        client.close()


def redact_password(url: str) -> str:
    """`url` with the password of its user part (redis://user:secret@host) replaced by ***."""
    scheme, sep, rest = url.partition("://")
    credentials, at, host = rest.rpartition("@")
    if not at or ":" not in credentials:
        return url
    return f"{scheme}{sep}{credentials.split(':', 1)[0]}:***@{host}"


def _serve(args: argparse.Namespace) -> int:
    from service.app import create_app
    from service.server import check_port_free, serve

    settings = settings_from_args(args)
    check_paths(settings)
    check_port_free(settings.host, settings.port)
    check_broker(settings)
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if settings.api_keys is None and settings.api_keys_file is None:
        logging.getLogger("service").warning(
            "no fleet API key is configured (HAPTICLINK_API_KEYS or HAPTICLINK_API_KEYS_FILE): every robot's "
            "session request will be refused (503)"
        )
    if settings.metrics_token is None:
        logging.getLogger("service").warning(
            "no metrics token is configured (HAPTICLINK_METRICS_TOKEN): GET /metrics refuses every scrape (403)"
        )
    # SIGINT/SIGTERM: the sessions end (operators told), then uvicorn stops accepting, lets open requests finish and
    # runs the lifespan shutdown.
    serve(create_app(settings), settings)
    return 0
