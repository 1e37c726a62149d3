"""The operator console: one static page (vanilla JS, no build step) and its texture renderer, shipped inside the
package."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources


@lru_cache(maxsize=1)
def page() -> str:
    """static/console.html; it reads ?session=…&token=… and opens WS /sessions/{id}/events itself."""
    return resources.files("service").joinpath("static/console.html").read_text(encoding="utf-8")


@lru_cache(maxsize=1)
def render_worklet() -> str:
    """static/render-worklet.js: the AudioWorklet that synthesises a served rendering model for the touch pad."""
    return resources.files("service").joinpath("static/render-worklet.js").read_text(encoding="utf-8")


@lru_cache(maxsize=1)
def model_codec() -> str:
    """static/model-codec.js: the compact model codec (texture_library/model_codec.py) for models pushed on the
    console's event socket."""
    return resources.files("service").joinpath("static/model-codec.js").read_text(encoding="utf-8")
