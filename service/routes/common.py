"""What the routers share: OpenAPI answer descriptions, and a request's media type."""

from __future__ import annotations

from typing import Any

from fastapi import Request

from service.schemas import ErrorOut


def media_type(request: Request) -> str:
    """The request's Content-Type without its parameters, lower case ("" when it has none)."""
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorOut} for code in codes}


def try_later(description: str) -> dict[int | str, dict[str, Any]]:
    """The documented 429 answer, with its Retry-After header."""
    return {
        429: {"model": ErrorOut, "description": description, "headers": {"Retry-After": {"schema": {"type": "string"}}}}
    }
