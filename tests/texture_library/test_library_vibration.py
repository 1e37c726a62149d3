"""VibrationModel: validation on construction and the .npz round trip."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel

ARRAYS = ("speeds", "forces", "triangles", "ar_lsf", "ma_lsf", "variance", "gain")


def assert_same_model(a: VibrationModel, b: VibrationModel) -> None:
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("name", "mu", "max_speed", "max_force", "rate_hz", "provenance", "extra"):
        assert getattr(a, name) == getattr(b, name), name
    assert (a.taps is None) == (b.taps is None)
    if a.taps is not None:
        np.testing.assert_array_equal(a.taps.speeds, b.taps.speeds)
        np.testing.assert_array_equal(a.taps.accel, b.taps.accel)


@pytest.mark.parametrize("fixture", ["model", "model_with_taps"])
def test_save_load_round_trip(fixture, request, tmp_path):
    model = request.getfixturevalue(fixture)
    loaded = VibrationModel.load(model.save(tmp_path / "m.npz"))
    assert_same_model(model, loaded)
    assert loaded.triangles.dtype == np.int64
    assert (loaded.ar_order, loaded.ma_order) == (4, 2)


def test_pure_ar_model_has_ma_order_zero(model, tmp_path):
    ar_only = dataclasses.replace(model, ma_lsf=np.zeros((model.speeds.size, 0)))
    assert ar_only.ma_order == 0
    assert VibrationModel.load(ar_only.save(tmp_path / "ar.npz")).ma_order == 0


@pytest.mark.parametrize(
    "change, message",
    [
        ({"speeds": np.zeros((3, 3))}, r"speeds must be 1-D with at least 3 grid points"),
        ({"speeds": np.array([0.0, 1.0])}, r"speeds must be 1-D with at least 3 grid points"),
        ({"forces": np.zeros(8)}, r"forces must have shape \(9,\), got \(8,\)"),
        ({"variance": np.zeros(10)}, r"variance must have shape \(9,\)"),
        ({"gain": np.ones((9, 1))}, r"gain must have shape \(9,\)"),
        ({"ar_lsf": np.full((8, 4), 1.0)}, r"ar_lsf must have shape \(9, order\), got \(8, 4\)"),
        ({"ma_lsf": np.full(9, 1.0)}, r"ma_lsf must have shape \(9, order\)"),
        ({"triangles": np.array([[0, 1]])}, r"triangles must have shape \(t, 3\), got \(1, 2\)"),
        ({"triangles": np.array([[0, 1, 9]])}, r"triangle indices must lie in \[0, 8\] \(0-based\), got \[0, 9\]"),
        ({"triangles": np.array([[-1, 1, 2]])}, r"triangle indices must lie in \[0, 8\]"),
        ({"triangles": np.array([[0.0, 1.0, 2.0]])}, r"triangles must be integer indices"),
        ({"variance": np.full(9, np.nan)}, r"variance contains NaN or Inf"),
        ({"speeds": np.array([0, 0, 0, 100, 100, 100, 200, 200, np.inf])}, r"speeds contains NaN or Inf"),
        ({"variance": -np.ones(9)}, r"variance must be ≥ 0"),
        ({"mu": 7.0}, r"mu must lie in \[0, 5\)"),
        ({"mu": float("nan")}, r"mu must lie in \[0, 5\)"),
        ({"max_speed": 0.0}, r"max_speed and max_force must be > 0"),
        ({"rate_hz": 0.0}, r"rate_hz must be > 0"),
    ],
)
def test_construction_names_every_problem(model, change, message):
    with pytest.raises(ValueError, match=message) as err:
        dataclasses.replace(model, **change)
    assert "vibration model 'square'" in str(err.value)


@pytest.mark.parametrize("field", ["ar_lsf", "ma_lsf"])
@pytest.mark.parametrize(
    "row",
    [
        lambda r: r[::-1],  # decreasing
        lambda r: np.concatenate([[r[0]], r[:-1]]),  # a repeated value
        lambda r: np.concatenate([[0.0], r[1:]]),  # touches 0
        lambda r: np.concatenate([r[:-1], [np.pi]]),  # touches π
    ],
    ids=["decreasing", "repeated", "zero", "pi"],
)
def test_lsf_rows_must_increase_strictly_inside_zero_pi(model, field, row):
    arr = np.array(getattr(model, field))
    arr[4] = row(arr[4])
    with pytest.raises(ValueError, match=f"{field} must increase strictly inside"):
        dataclasses.replace(model, **{field: arr})


def test_taps_are_validated():
    with pytest.raises(ValueError, match=r"taps: need speeds \(k,\) and accel \(k, n\)"):
        TapSet(np.array([1.0, 2.0]), np.zeros((3, 100)))
    with pytest.raises(ValueError, match="k ≥ 1"):
        TapSet(np.zeros(0), np.zeros((0, 100)))
    with pytest.raises(ValueError, match=r"taps: 100 sample\(s\) are NaN or Inf"):
        TapSet(np.array([1.0]), np.full((1, 100), np.nan))
    with pytest.raises(ValueError, match="taps: speeds contain NaN or Inf"):
        TapSet(np.array([np.inf]), np.zeros((1, 100)))
    with pytest.raises(ValueError, match="taps: samples must be numbers"):
        TapSet(np.array([1.0]), np.full((1, 100), "x"))


def test_load_names_what_is_wrong_with_the_file(model, tmp_path):
    with pytest.raises(ValueError, match="hapticlink-vibration-model file not found"):
        VibrationModel.load(tmp_path / "absent.npz")

    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="not a readable .npz file"):
        VibrationModel.load(tmp_path / "text.npz")

    np.savez(tmp_path / "noheader.npz", speeds=model.speeds)
    with pytest.raises(ValueError, match="no header"):
        VibrationModel.load(tmp_path / "noheader.npz")

    path = model.save(tmp_path / "m.npz")
    with np.load(path) as z:
        arrays = dict(z)
    header = json.loads(str(arrays.pop("header")))

    def rewrite(name, header_change=None, drop=()):
        h = {**header, **(header_change or {})}
        kept = {k: v for k, v in arrays.items() if k not in drop}
        np.savez(tmp_path / name, header=np.array(json.dumps(h)), **kept)
        return tmp_path / name

    with pytest.raises(ValueError, match="format is 'other'"):
        VibrationModel.load(rewrite("fmt.npz", {"format": "other"}))
    with pytest.raises(ValueError, match="unsupported hapticlink-vibration-model version 2"):
        VibrationModel.load(rewrite("ver.npz", {"version": 2}))
    with pytest.raises(ValueError, match=r"missing \['ar_lsf'\]"):
        VibrationModel.load(rewrite("noar.npz", drop=("ar_lsf",)))
    h = dict(header)
    del h["mu"]
    np.savez(tmp_path / "nomu.npz", header=np.array(json.dumps(h)), **arrays)
    with pytest.raises(ValueError, match=r"missing \['mu'\]"):
        VibrationModel.load(tmp_path / "nomu.npz")
