"""TexNet crowd ratings (0–100, "more of it") → hapticlink's bipolar attributes (−100…100).

    rough_smooth    = 100 − 2·roughness    (very rough → −100, the "rough" pole)
    flat_bumpy      = 2·bumpiness − 100    (very bumpy → +100, the "bumpy" pole)
    sticky_slippery = 100 − 2·stickiness   (very sticky → −100)
    hard_soft       = 100 − 2·hardness     (very hard → −100)
Warmness has no hapticlink attribute and is dropped. An error of e on the
bipolar scale is e/2 on TexNet's 0–100 scale, the scale metrics are reported on.
"""

from __future__ import annotations

#: TexNet attribute → (hapticlink attribute, sign of (2·r − 100))
TEXNET_TO_BIPOLAR: dict[str, tuple[str, int]] = {
    "roughness": ("rough_smooth", -1),
    "bumpiness": ("flat_bumpy", +1),
    "stickiness": ("sticky_slippery", -1),
    "hardness": ("hard_soft", -1),
}
IGNORED = ("warmness",)


def to_bipolar(attribute: str, rating: float) -> tuple[str, float]:
    """(hapticlink attribute, bipolar rating) for one TexNet rating."""
    if attribute not in TEXNET_TO_BIPOLAR:
        raise ValueError(f"unknown TexNet attribute {attribute!r}; expected one of {sorted(TEXNET_TO_BIPOLAR)}")
    if not 0.0 <= rating <= 100.0:
        raise ValueError(f"TexNet rating must lie in [0, 100], got {rating}")
    name, sign = TEXNET_TO_BIPOLAR[attribute]
    return name, sign * (2.0 * rating - 100.0)


def read_texnet_ratings(path) -> dict[str, dict[str, list[tuple[str, int, float]]]]:
    """ratings.csv (texture, rater, presentation, attribute, rating)
    → {texture: {attr: [(rater, presentation, bipolar)]}}."""
    import csv

    out: dict[str, dict[str, list[tuple[str, int, float]]]] = {}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [
            c for c in ("texture", "rater", "presentation", "attribute", "rating") if c not in (reader.fieldnames or [])
        ]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}")
        for line, r in enumerate(reader, start=2):
            if r["attribute"] in IGNORED:
                continue
            try:
                attr, value = to_bipolar(r["attribute"], float(r["rating"]))
                presentation = int(r["presentation"])
            except ValueError as exc:
                raise ValueError(f"{path} line {line}: {exc}") from None
            out.setdefault(r["texture"], {}).setdefault(attr, []).append((r["rater"], presentation, value))
    return out
