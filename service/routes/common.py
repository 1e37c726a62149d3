"""OpenAPI answer descriptions the routers share."""

from __future__ import annotations

from typing import Any

from service.schemas import ErrorOut


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorOut} for code in codes}


def try_later(description: str) -> dict[int | str, dict[str, Any]]:
    """The documented 429 answer, with its Retry-After header."""
    return {
        429: {"model": ErrorOut, "description": description, "headers": {"Retry-After": {"schema": {"type": "string"}}}}
    }
