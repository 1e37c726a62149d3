"""Texture families: samples of one product line, which leave-one-texture-out keeps in training.

Textures whose names differ only in a trailing number (HaTT's carpet_1 / carpet_3 / carpet_4, floortile_1 …
floortile_7, sandpaper_100 / sandpaper_220) are one family. Leaving one texture out keeps its siblings in the
training set, so the number says how well a model reads a new *sample*; leaving its family out as well says how
well it reads a new *material* (`hapticlink evaluate --leave-out family`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

LEAVE_OUT = ("texture", "family")
_NUMBER_SUFFIX = re.compile(r"_\d+$")


def family_of(texture: str) -> str:
    """A texture's family: its name without a trailing `_<digits>` ('carpet_3' → 'carpet', 'sandpaper_100' →
    'sandpaper'); a name without one is a family of its own ('abs_plastic', 't017')."""
    if not isinstance(texture, str) or not texture:
        raise ValueError(f"a texture name must be a non-empty string, got {texture!r}")
    family = _NUMBER_SUFFIX.sub("", texture)
    if not family:
        raise ValueError(f"texture name {texture!r} is only a number suffix: it names no family")
    return family


def left_out_with(textures: Sequence[str], leave_out: str) -> list[tuple[int, ...]]:
    """For each texture, the other textures its fold also keeps out of training: none (`leave_out` "texture"),
    or its family's other members ("family"), as indices into `textures`."""
    if leave_out not in LEAVE_OUT:
        raise ValueError(f"leave_out must be one of {LEAVE_OUT}, got {leave_out!r}")
    if leave_out == "texture":
        return [() for _ in textures]
    families = [family_of(t) for t in textures]
    return [tuple(j for j, g in enumerate(families) if g == f and j != i) for i, f in enumerate(families)]


def with_siblings(textures: Sequence[str]) -> list[int]:
    """Indices of the textures whose family has another member among `textures`."""
    return [i for i, others in enumerate(left_out_with(textures, "family")) if others]
