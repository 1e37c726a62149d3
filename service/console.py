"""The operator console: one static page (vanilla JS, no build step) shipped inside the package."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources


@lru_cache(maxsize=1)
def page() -> str:
    """static/console.html; it reads ?session=…&token=… and opens WS /sessions/{id}/events itself."""
    return resources.files("service").joinpath("static/console.html").read_text(encoding="utf-8")
