"""A pydantic ValidationError as one line for the command line, each field named by the flag or variable that set it."""

from __future__ import annotations

from collections.abc import Callable

from pydantic import ValidationError


def named_errors(exc: ValidationError, name: Callable[[str], str], whole: str) -> str:
    """A pydantic ValidationError as 'NAME: message; …', each field named by `name` (the flag or variable that set
    it) rather than by pydantic's field path; `whole` names an error of the model as a whole."""
    return "; ".join(f"{name(str(e['loc'][0])) if e['loc'] else whole}: {e['msg']}" for e in exc.errors())
