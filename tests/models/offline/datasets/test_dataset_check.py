"""`check_dataset` and `hapticlink dataset check`: a clean build passes; every corruption is named precisely."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from models.offline.datasets.check import check_dataset
from service.cli import main as hapticlink

TEX = "synth_000"  # rated
RATED2 = "synth_001"  # rated
WITHHELD = "synth_002"


def only(problems: list[str]) -> str:
    assert len(problems) == 1, problems
    return problems[0]


def rec_path(root: Path, tid: str = TEX) -> Path:
    return root / "textures" / tid / "recording_000.npz"


def img_path(root: Path, tid: str = TEX) -> Path:
    return root / "textures" / tid / "image_000.png"


def write_recording(path: Path, accel: np.ndarray, rate=1000.0, units="m/s^2") -> None:
    n = accel.shape[0]
    header = {
        "format": "hapticlink-recording",
        "version": 1,
        "channels": {
            "accel": {"rate_hz": rate, "units": units},
            "force": {"rate_hz": 1000.0, "units": "N"},
            "speed": {"rate_hz": 1000.0, "units": "mm/s"},
        },
    }
    np.savez(path, header=np.array(json.dumps(header)), accel=accel, force=np.ones(n), speed=np.full(n, 50.0))


def edit_csv(path: Path, edit) -> None:
    """edit(rows) → rows, rows being lists of strings including the header row."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows(edit(rows))


def test_a_fresh_synthetic_build_is_clean(synthetic_dataset):
    assert check_dataset(synthetic_dataset) == []
    assert check_dataset(synthetic_dataset, deep=False) == []


def test_cli_check_passes_a_clean_dataset(synthetic_dataset, capsys):
    assert hapticlink(["dataset", "check", str(synthetic_dataset)]) == 0
    assert capsys.readouterr().out.strip() == f"{synthetic_dataset}: ok"


def test_cli_check_fails_and_prints_the_problem(dataset_copy, capsys):
    rec_path(dataset_copy).unlink()
    assert hapticlink(["dataset", "check", str(dataset_copy)]) == 1
    err = capsys.readouterr().err
    assert f"texture '{TEX}': recording file missing: {rec_path(dataset_copy)}" in err
    assert f"{dataset_copy}: 1 problem(s)" in err


# ---- missing files ---------------------------------------------------------------------------------
def test_missing_textures_csv(dataset_copy):
    (dataset_copy / "textures.csv").unlink()
    assert only(check_dataset(dataset_copy)) == f"missing file: {dataset_copy / 'textures.csv'}"


def test_missing_ratings_csv(dataset_copy):
    (dataset_copy / "ratings.csv").unlink()
    assert only(check_dataset(dataset_copy)) == f"missing file: {dataset_copy / 'ratings.csv'}"


def test_missing_dataset_json(dataset_copy):
    (dataset_copy / "dataset.json").unlink()
    assert only(check_dataset(dataset_copy)) == f"{dataset_copy / 'dataset.json'}: missing file"


def test_missing_recording(dataset_copy):
    rec_path(dataset_copy).unlink()
    assert only(check_dataset(dataset_copy)) == f"texture '{TEX}': recording file missing: {rec_path(dataset_copy)}"


def test_missing_image(dataset_copy):
    img_path(dataset_copy).unlink()
    assert only(check_dataset(dataset_copy)) == f"texture '{TEX}': image file missing: {img_path(dataset_copy)}"


def test_missing_meta(dataset_copy):
    meta = dataset_copy / "textures" / TEX / "meta.json"
    meta.unlink()
    assert only(check_dataset(dataset_copy)) == f"texture '{TEX}': missing {meta}"


def test_meta_that_is_not_json(dataset_copy):
    meta = dataset_copy / "textures" / TEX / "meta.json"
    meta.write_text("{images: []")
    assert only(check_dataset(dataset_copy)).startswith(f"texture '{TEX}': {meta}: invalid JSON (")


def test_the_quick_check_still_sees_missing_files(dataset_copy):
    img_path(dataset_copy).unlink()
    assert "image file missing" in only(check_dataset(dataset_copy, deep=False))


# ---- recordings ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "accel, rate, fault",
    [
        (np.zeros((2000, 2)), 1000.0, "accel: shape must be (n, 3), got (2000, 2)"),
        (np.zeros(2000), 1000.0, "accel: shape must be (n, 3), got (2000,)"),
        (
            np.zeros((2000, 3)),
            0,
            "accel: sample rate must lie in [10, 100000] Hz, got 0 (a sample interval of 0.01 to 100 ms)",
        ),
        (
            np.zeros((2000, 3)),
            -1000.0,
            "accel: sample rate must lie in [10, 100000] Hz, got -1000 (a sample interval of 0.01 to 100 ms)",
        ),
        (
            np.zeros((2000, 3)),
            1e9,
            "accel: sample rate must lie in [10, 100000] Hz, got 1e+09 (a sample interval of 0.01 to 100 ms)",
        ),
        (np.zeros((2000, 3)), None, "accel: sample rate must be a finite number, got None"),
        (np.where(np.arange(6000).reshape(2000, 3) == 700, np.nan, 0.0), 1000.0, "accel: 1 sample(s) are NaN or Inf"),
        (np.where(np.arange(6000).reshape(2000, 3) < 2, np.inf, 0.0), 1000.0, "accel: 2 sample(s) are NaN or Inf"),
    ],
)
def test_bad_recording_is_named(dataset_copy, accel, rate, fault):
    write_recording(rec_path(dataset_copy), accel, rate)
    assert only(check_dataset(dataset_copy)) == f"texture '{TEX}': {rec_path(dataset_copy)}: {fault}"


def test_recording_too_short(dataset_copy):
    write_recording(rec_path(dataset_copy), np.zeros((300, 3)))
    assert only(check_dataset(dataset_copy)) == (
        f"texture '{TEX}': {rec_path(dataset_copy)} is too short (0.300 s < one 0.5 s window)"
    )


def test_recording_that_is_not_npz(dataset_copy):
    rec_path(dataset_copy).write_text("accel,force\n1,2\n")
    assert "not a readable .npz file" in only(check_dataset(dataset_copy))


def test_recordings_are_not_decoded_by_the_quick_check(dataset_copy):
    write_recording(rec_path(dataset_copy), np.zeros((2000, 2)))
    assert check_dataset(dataset_copy, deep=False) == []


# ---- images ------------------------------------------------------------------------------------------
def test_image_that_is_not_an_image(dataset_copy):
    img_path(dataset_copy).write_text("this is not a PNG")
    problem = only(check_dataset(dataset_copy))
    assert problem.startswith(f"texture '{TEX}': {img_path(dataset_copy)} is not a readable image (")


def test_image_too_small(dataset_copy):
    Image.fromarray(np.zeros((100, 300), np.uint8)).save(img_path(dataset_copy))
    assert only(check_dataset(dataset_copy)) == (
        f"texture '{TEX}': {img_path(dataset_copy)} is 300×100 px, smaller than one 224×224 patch"
    )


# ---- ratings -----------------------------------------------------------------------------------------
def set_cell(root: Path, line: int, column: str, value: str) -> None:
    def edit(rows):
        rows[line - 1][rows[0].index(column)] = value
        return rows

    edit_csv(root / "ratings.csv", edit)


@pytest.mark.parametrize(
    "column, value, fault",
    [
        (
            "attribute",
            "warmness",
            "unknown attribute 'warmness'; expected one of "
            "['rough_smooth', 'flat_bumpy', 'sticky_slippery', 'hard_soft']",
        ),
        ("rating", "150", "rating 150 out of range [-100, 100]"),
        ("rating", "-100.5", "rating -100.5 out of range [-100, 100]"),
        ("rating", "abc", "rating 'abc' is not a number"),
        ("rating", "", "rating '' is not a number"),
        ("rating", "nan", "rating is nan (NaN/Inf)"),
        ("presentation", "0", "presentation '0' must be an integer ≥ 1"),
        ("presentation", "first", "presentation 'first' must be an integer ≥ 1"),
        ("texture", "ghost", "unknown texture 'ghost'"),
    ],
)
def test_bad_rating_row_is_named_with_its_line(dataset_copy, column, value, fault):
    set_cell(dataset_copy, 3, column, value)
    assert only(check_dataset(dataset_copy)) == f"{dataset_copy / 'ratings.csv'} line 3: {fault}"


def test_rated_yes_without_ratings(dataset_copy):
    edit_csv(dataset_copy / "ratings.csv", lambda rows: [r for r in rows if r[0] != RATED2])
    assert only(check_dataset(dataset_copy)) == (
        f"{dataset_copy / 'ratings.csv'}: texture '{RATED2}' is marked rated=yes but has no ratings"
    )


def test_withheld_texture_with_a_rating(dataset_copy):
    edit_csv(dataset_copy / "ratings.csv", lambda rows: rows + [[WITHHELD, "r000", "1", "hard_soft", "10"]])
    line = sum(1 for _ in open(dataset_copy / "ratings.csv"))
    assert only(check_dataset(dataset_copy)) == (
        f"{dataset_copy / 'ratings.csv'} line {line}: texture '{WITHHELD}' is marked rated='withheld' but has a rating"
    )


def test_the_same_rating_twice(dataset_copy):
    edit_csv(dataset_copy / "ratings.csv", lambda rows: rows + [rows[1]])
    line = sum(1 for _ in open(dataset_copy / "ratings.csv"))
    problem = only(check_dataset(dataset_copy))
    assert problem.startswith(
        f"{dataset_copy / 'ratings.csv'} line {line}: rater 'r000' rated 'rough_smooth' of '{TEX}' "
        "in presentation 1 again (first on line 2)"
    )


def test_a_repeat_in_presentation_two_is_fine(dataset_copy):
    edit_csv(dataset_copy / "ratings.csv", lambda rows: rows + [rows[1][:2] + ["2"] + rows[1][3:]])
    assert check_dataset(dataset_copy) == []


# ---- textures.csv and the header ----------------------------------------------------------------------
def test_texture_listed_twice(dataset_copy):
    edit_csv(dataset_copy / "textures.csv", lambda rows: rows + [rows[1]])
    assert (
        only(check_dataset(dataset_copy)) == f"{dataset_copy / 'textures.csv'} line 5: texture '{TEX}' is listed twice"
    )


@pytest.mark.parametrize(
    "column, value, fault",
    [
        ("rated", "maybe", "rated is 'maybe', expected one of ['yes', 'withheld', 'no']"),
        ("texture", "../escape", "texture id '../escape' is not a valid name (letters, digits, _ . -)"),
    ],
)
def test_bad_texture_row(dataset_copy, column, value, fault):
    def edit(rows):
        rows[3][rows[0].index(column)] = value  # synth_002, the withheld one: no ratings depend on it
        return rows

    edit_csv(dataset_copy / "textures.csv", edit)
    assert only(check_dataset(dataset_copy)) == f"{dataset_copy / 'textures.csv'} line 4: {fault}"


def test_missing_column(dataset_copy):
    edit_csv(dataset_copy / "textures.csv", lambda rows: [r[:3] for r in rows])
    problem = only(check_dataset(dataset_copy))
    assert problem.startswith(f"{dataset_copy / 'textures.csv'}: missing column(s) ['rated']")


@pytest.mark.parametrize(
    "key, value, fault",
    [
        ("version", 2, "version is 2, expected 1"),
        ("format", "zip", "format is 'zip', expected 'hapticlink-dataset'"),
        ("rating_scale", [0, 100], "rating_scale is [0, 100], expected [-100.0, 100.0]"),
    ],
)
def test_bad_header(dataset_copy, key, value, fault):
    path = dataset_copy / "dataset.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), key: value}))
    assert only(check_dataset(dataset_copy)) == f"{path}: {fault}"


def test_corrupt_vibration_model(dataset_copy):
    path = dataset_copy / "textures" / TEX / "vibration.npz"
    path.write_bytes(path.read_bytes()[:200])
    problem = only(check_dataset(dataset_copy))
    assert problem.startswith(f"texture '{TEX}': vibration model {path}: ")


def test_every_problem_is_reported_not_just_the_first(dataset_copy):
    img_path(dataset_copy).unlink()
    rec_path(dataset_copy, RATED2).unlink()
    set_cell(dataset_copy, 2, "rating", "999")
    assert len(check_dataset(dataset_copy)) == 3
