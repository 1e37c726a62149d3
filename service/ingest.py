"""The ingest step: wire bytes → SampleBlock or TapBlock → the session's admission → the acknowledgement, with outcomes counted.

HTTP `POST /blocks` and the ingest WebSocket both call `receive_block`, so a block is decoded and
validated once, in one place, whichever way it came.
"""

from __future__ import annotations

import json

from drivers.blocks import Block, decode_binary, decode_json
from service.errors import ServiceError
from service.metrics import ServiceMetrics
from service.session import Session

#: what a malformed payload can raise inside the shared decoders (huge ints overflow, deep nesting recurses)
DECODE_ERRORS = (ValueError, TypeError, OverflowError, RecursionError)


def receive_block(metrics: ServiceMetrics, session: Session, payload: bytes, binary: bool, arrived_ns: int) -> dict:
    """Decode and admit one block → its acknowledgement; ServiceError (400/422/429) otherwise. Counts outcomes."""
    try:
        block = decode_block(payload, binary)
        ack = session.ingest(block, arrived_ns)
    except ServiceError as exc:
        if exc.status == 429:
            metrics.blocks.inc(outcome="refused")
        else:
            count_rejected(metrics, session)
        raise
    metrics.blocks.inc(outcome="duplicate" if ack["duplicate"] else "accepted")
    return ack


def count_rejected(metrics: ServiceMetrics, session: Session) -> None:
    metrics.blocks.inc(outcome="rejected")
    session.counters.blocks_rejected += 1


def decode_block(payload: bytes, binary: bool) -> Block:
    """Wire bytes → SampleBlock | TapBlock; ServiceError 400 (not JSON) or 422 (not a valid block) with the decoder's message."""
    try:
        if binary:
            return decode_binary(payload)
        try:
            obj = json.loads(payload, parse_int=_json_int)
        except (ValueError, RecursionError) as exc:
            raise ServiceError(400, f"body is not valid JSON: {exc}") from None
        return decode_json(obj)
    except DECODE_ERRORS as exc:
        if isinstance(exc, ValueError):
            detail = str(exc)
        elif isinstance(exc, OverflowError):
            detail = f"a number in the block is out of range ({exc})"
        else:
            detail = f"invalid block ({type(exc).__name__}: {exc})"
        raise ServiceError(422, detail) from None


def _json_int(text: str) -> int | float:
    """JSON integers beyond float range become ±inf, so the validators name the field instead of overflowing."""
    value = int(text)
    if abs(value) > 2**1023:
        return float("inf") if value > 0 else float("-inf")
    return value
