"""The size limit of a hapticlink .npz: save_npz writes only what load_npz reads."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

import texture_library.npzfile as npzfile
from texture_library.npzfile import load_npz, save_npz

ARRAYS = {"a": np.zeros((1000, 3), np.float32), "b": np.arange(500, dtype=np.int64)}


def _declared(path) -> int:
    with zipfile.ZipFile(path) as z:
        return sum(info.file_size for info in z.infolist())


def test_save_refuses_what_load_would_refuse_and_writes_nothing(tmp_path, monkeypatch):
    reference = save_npz(tmp_path / "ref.npz", "fmt", 1, {"k": "v"}, ARRAYS)
    size = _declared(reference)
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", size - 1)
    path = tmp_path / "big.npz"
    with pytest.raises(ValueError) as err:
        save_npz(path, "fmt", 1, {"k": "v"}, ARRAYS)
    assert str(err.value) == (
        f"{path}: would hold {size:,} bytes ({size / 2**20:.1f} MiB) once decompressed; at most {size - 1:,} bytes "
        f"({(size - 1) / 2**20:.1f} MiB) are read, so it is not written"
    )
    assert not path.exists()


def test_a_file_exactly_at_the_limit_is_written_and_read(tmp_path, monkeypatch):
    size = _declared(save_npz(tmp_path / "ref.npz", "fmt", 1, {"k": "v"}, ARRAYS))
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", size)
    header, arrays = load_npz(save_npz(tmp_path / "at.npz", "fmt", 1, {"k": "v"}, ARRAYS), "fmt", 1)
    assert header == {"format": "fmt", "version": 1, "k": "v"}
    np.testing.assert_array_equal(arrays["b"], ARRAYS["b"])


def test_a_file_just_over_the_limit_does_not_read_as_equal_to_it(tmp_path, monkeypatch):
    """At 1 GiB + 1 byte, whole MiB printed both sizes as "1024 MiB"."""
    path = save_npz(tmp_path / "f.npz", "fmt", 1, {}, ARRAYS)
    size = _declared(path)
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", size - 1)
    with pytest.raises(ValueError) as err:
        load_npz(path, "fmt", 1)
    assert str(err.value) == (
        f"{path}: holds {size:,} bytes ({size / 2**20:.1f} MiB) once decompressed; at most {size - 1:,} bytes "
        f"({(size - 1) / 2**20:.1f} MiB) are read"
    )


@pytest.mark.parametrize(
    "array",
    [
        np.zeros((0, 3)),
        np.asfortranarray(np.ones((40, 7), np.float32)),
        np.ones((10, 4))[:, ::2],
        np.array("text"),
        pytest.param(  # a header past 64 KiB: NumPy writes format 2.0 (and says so)
            np.zeros(2, dtype=[(f"field_{i}", "u1") for i in range(4000)]),
            marks=pytest.mark.filterwarnings("ignore:Stored array in format 2.0"),
        ),
    ],
    ids=["empty", "fortran", "strided", "string", "long-header"],
)
def test_the_size_counted_on_save_is_the_size_declared_in_the_file(tmp_path, monkeypatch, array):
    size = _declared(save_npz(tmp_path / "ref.npz", "fmt", 1, {}, {"x": array}))
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", size)
    save_npz(tmp_path / "at.npz", "fmt", 1, {}, {"x": array})
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", size - 1)
    with pytest.raises(ValueError, match="so it is not written"):
        save_npz(tmp_path / "over.npz", "fmt", 1, {}, {"x": array})
