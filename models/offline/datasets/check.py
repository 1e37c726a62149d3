"""Validate a dataset directory and name exactly what is wrong.

`check_dataset(DIR)` returns a list of problems (empty when the dataset is
valid); `hapticlink dataset check DIR` prints them and exits non-zero.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from models.offline.datasets.format import (
    FORMAT,
    MODALITIES,
    RATED_VALUES,
    RATING_COLUMNS,
    TEXTURE_COLUMNS,
    VERSION,
    Dataset,
    load_recording,
    read_csv,
)
from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN
from texture_library.vibration import VibrationModel

MIN_IMAGE_PX = 224  # one backbone patch
MIN_RECORDING_S = 0.5  # one feature window
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def check_dataset(root: str | Path, *, deep: bool = True) -> list[str]:
    """Problems found in the dataset at root, each a sentence naming the file and the fault.

    deep=False skips loading recordings and decoding images (fast structural check).
    """
    root = Path(root)
    problems: list[str] = []
    if not root.is_dir():
        return [f"{root}: not a directory"]
    header_path = root / "dataset.json"
    if not header_path.is_file():
        return [f"{header_path}: missing file"]
    try:
        header = json.loads(header_path.read_text())
    except json.JSONDecodeError as exc:
        return [f"{header_path}: invalid JSON ({exc})"]
    if not isinstance(header, dict):
        return [f"{header_path}: expected a JSON object"]
    if header.get("format") != FORMAT:
        problems.append(f"{header_path}: format is {header.get('format')!r}, expected {FORMAT!r}")
    if header.get("version") != VERSION:
        problems.append(f"{header_path}: version is {header.get('version')!r}, expected {VERSION}")
    if header.get("attributes") != list(ATTRIBUTES):
        problems.append(f"{header_path}: attributes are {header.get('attributes')!r}, expected {list(ATTRIBUTES)}")
    if header.get("rating_scale") != [RATING_MIN, RATING_MAX]:
        problems.append(
            f"{header_path}: rating_scale is {header.get('rating_scale')!r}, expected {[RATING_MIN, RATING_MAX]}"
        )
    modalities = header.get("modalities", list(MODALITIES))
    if not isinstance(modalities, list) or not modalities or any(m not in MODALITIES for m in modalities):
        problems.append(
            f"{header_path}: modalities is {modalities!r}, expected a non-empty subset of {list(MODALITIES)}"
        )
    elif "images" not in modalities:
        problems.append(f"{header_path}: modalities {modalities!r} has no images; every texture needs an image")
    if problems:
        return problems

    try:
        texture_rows = read_csv(root / "textures.csv", TEXTURE_COLUMNS)
    except ValueError as exc:
        return problems + [str(exc)]
    rated: dict[str, str] = {}
    for line, row in enumerate(texture_rows, start=2):
        tid = row["texture"]
        where = f"{root / 'textures.csv'} line {line}"
        if not _ID.match(tid or ""):
            problems.append(f"{where}: texture id {tid!r} is not a valid name (letters, digits, _ . -)")
            continue
        if tid in rated:
            problems.append(f"{where}: texture {tid!r} is listed twice")
        if row["rated"] not in RATED_VALUES:
            problems.append(f"{where}: rated is {row['rated']!r}, expected one of {list(RATED_VALUES)}")
        rated[tid] = row["rated"]
    if not rated:
        problems.append(f"{root / 'textures.csv'}: no textures")

    problems += _check_ratings(root, rated)
    dataset = Dataset(root)
    for tid in rated:
        problems += _check_texture(dataset, tid, deep, image_only="recordings" not in modalities)
    return problems


def _check_ratings(root: Path, rated: dict[str, str]) -> list[str]:
    path = root / "ratings.csv"
    try:
        rows = read_csv(path, RATING_COLUMNS)
    except ValueError as exc:
        return [str(exc)]
    problems = []
    seen: Counter = Counter()
    first_line: dict[tuple[str, str, str, str], int] = {}
    for line, row in enumerate(rows, start=2):
        where = f"{path} line {line}"
        tid = row["texture"]
        if tid not in rated:
            problems.append(f"{where}: unknown texture {tid!r}")
            continue
        if rated[tid] != "yes":
            problems.append(f"{where}: texture {tid!r} is marked rated={rated[tid]!r} but has a rating")
        if row["attribute"] not in ATTRIBUTES:
            problems.append(f"{where}: unknown attribute {row['attribute']!r}; expected one of {list(ATTRIBUTES)}")
        try:
            value = float(row["rating"])
        except (TypeError, ValueError):
            problems.append(f"{where}: rating {row['rating']!r} is not a number")
            continue
        if not math.isfinite(value):
            problems.append(f"{where}: rating is {row['rating']} (NaN/Inf)")
        elif not (RATING_MIN <= value <= RATING_MAX):
            problems.append(f"{where}: rating {value:g} out of range [{RATING_MIN:g}, {RATING_MAX:g}]")
        if not (row["presentation"] or "").isdigit() or int(row["presentation"]) < 1:
            problems.append(f"{where}: presentation {row['presentation']!r} must be an integer ≥ 1")
        key = (tid, row["rater"], row["presentation"], row["attribute"])
        if key in first_line:
            problems.append(
                f"{where}: rater {row['rater']!r} rated {row['attribute']!r} of {tid!r} in presentation "
                f"{row['presentation']} again (first on line {first_line[key]}); use presentation 2, 3, … for repeats"
            )
        else:
            first_line[key] = line
        seen[tid] += 1
    for tid, status in rated.items():
        if status == "yes" and seen[tid] == 0:
            problems.append(f"{path}: texture {tid!r} is marked rated=yes but has no ratings")
    return problems


def _check_texture(dataset: Dataset, tid: str, deep: bool, image_only: bool = False) -> list[str]:
    problems = []
    try:
        meta = dataset.meta(tid)  # its ValueError names the texture and the file
    except ValueError as exc:
        return [str(exc)]
    if image_only and meta.recordings:
        problems.append(
            f"texture {tid!r}: lists recordings in meta.json, but dataset.json says the dataset is image-only "
            f"(modalities {list(dataset.modalities)})"
        )
    elif not image_only and not meta.recordings:
        problems.append(f"texture {tid!r}: no recordings listed in meta.json")
    if not meta.images:
        problems.append(f"texture {tid!r}: no images listed in meta.json")
    for path in _present(dataset, tid, meta.recordings, "recording", problems):
        if deep:
            try:
                rec = load_recording(path)
            except ValueError as exc:
                problems.append(f"texture {tid!r}: {exc}")
                continue
            if rec.duration_s < MIN_RECORDING_S:
                problems.append(
                    f"texture {tid!r}: {path} is too short ({rec.duration_s:.3f} s < one {MIN_RECORDING_S} s window)"
                )
    for path in _present(dataset, tid, meta.images, "image", problems):
        if deep:
            problems += _check_image(tid, path)
    if meta.vibration_model is not None:
        path = dataset.resolve(tid, meta.vibration_model)
        try:
            VibrationModel.load(path)
        except (ValueError, KeyError, OSError) as exc:
            problems.append(f"texture {tid!r}: vibration model {path}: {exc}")
    return problems


def _present(dataset: Dataset, tid: str, names: list[str], what: str, problems: list[str]) -> list[Path]:
    """The files `names` of texture `tid` that exist; a problem ("<what> file missing") for each that does not."""
    paths = [dataset.resolve(tid, name) for name in names]
    problems += [f"texture {tid!r}: {what} file missing: {p}" for p in paths if not p.is_file()]
    return [p for p in paths if p.is_file()]


def _check_image(tid: str, path: Path) -> list[str]:
    try:
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            w, h = im.size
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        return [f"texture {tid!r}: {path} is not a readable image ({exc})"]
    if min(w, h) < MIN_IMAGE_PX:
        return [f"texture {tid!r}: {path} is {w}×{h} px, smaller than one {MIN_IMAGE_PX}×{MIN_IMAGE_PX} patch"]
    return []
