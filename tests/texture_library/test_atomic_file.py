import numpy as np
import pytest

from texture_library.atomic_file import atomic_path, write_bytes, write_text


def test_a_written_file_replaces_the_old_one_whole_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "library.json"
    write_text(target, "old")
    write_text(target, "new ✓")
    assert target.read_text(encoding="utf-8") == "new ✓"
    assert sorted(p.name for p in target.parent.iterdir()) == ["library.json"]
    write_bytes(target, b"\x00\x01")
    assert target.read_bytes() == b"\x00\x01"


def test_a_failed_write_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    target = tmp_path / "results.json"
    write_text(target, "old")
    with pytest.raises(RuntimeError, match="disk on fire"):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk on fire")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_the_temporary_keeps_the_suffix_so_numpy_writes_where_it_is_told(tmp_path):
    target = tmp_path / "cache.npz"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".npz" and tmp.parent == tmp_path and tmp.name.startswith(".")
        np.savez(tmp, x=np.arange(3))
    with np.load(target) as z:
        np.testing.assert_array_equal(z["x"], np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["cache.npz"]


def test_two_temporaries_for_one_target_differ(tmp_path):
    with atomic_path(tmp_path / "a.bin") as one, atomic_path(tmp_path / "a.bin") as two:
        one.write_bytes(b"1")
        two.write_bytes(b"2")
        assert one != two
    assert (tmp_path / "a.bin").read_bytes() == b"1"  # the last rename wins: the outer block ends last
