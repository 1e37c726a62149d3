"""models.offline.provenance: digests of files and trees, where an input lives, and the check that finds a
changed, a missing or an uncheckable input."""

from __future__ import annotations

import hashlib
import json

import pytest

from models.offline import provenance as prov


@pytest.fixture
def clone(tmp_path, monkeypatch):
    """A repository root with ../shared beside it."""
    repo, shared = tmp_path / "repo", tmp_path / "shared"
    (repo / "reports").mkdir(parents=True)
    (shared / "data" / "src").mkdir(parents=True)
    monkeypatch.setattr(prov, "REPO_ROOT", repo)
    monkeypatch.setattr(prov, "SHARED_ROOT", shared)
    return repo, shared


def test_file_and_tree_digests_follow_names_and_bytes(tmp_path):
    (tmp_path / "a.txt").write_bytes(b"abc")
    assert prov.file_sha256(tmp_path / "a.txt") == hashlib.sha256(b"abc").hexdigest()
    tree = prov.tree_sha256(tmp_path)
    (tmp_path / "a.txt").rename(tmp_path / "b.txt")
    renamed = prov.tree_sha256(tmp_path)
    (tmp_path / "b.txt").write_bytes(b"abd")
    assert len({tree, renamed, prov.tree_sha256(tmp_path)}) == 3
    with pytest.raises(ValueError, match="no such file"):
        prov.path_sha256(tmp_path / "nothing")


def test_inputs_are_stored_relative_to_the_repository(clone):
    repo, shared = clone
    (repo / "reports" / "r.json").write_text("{}")
    (repo / "data").mkdir()
    (repo / "data" / "dataset.json").write_text("{}")
    assert prov.locate(repo / "reports" / "r.json") == ("repo", "reports/r.json")
    assert prov.locate(repo / "data" / "dataset.json") == ("built", "data/dataset.json")
    assert prov.locate(shared / "data" / "src") == ("shared", "../shared/data/src")


def test_a_dataset_names_its_manifest_and_its_shared_source(clone):
    repo, shared = clone
    (shared / "data" / "src" / "ratings.csv").write_text("t,1\n")
    ds = repo / "data" / "ds"
    ds.mkdir(parents=True)
    # built on another checkout: its absolute source path is found again under this clone's ../shared
    (ds / "dataset.json").write_text(json.dumps({"build": {"src": "/elsewhere/shared/data/src"}}))
    inputs = prov.dataset_inputs(ds)
    assert [(i.kind, i.path) for i in inputs] == [("built", "data/ds/dataset.json"), ("shared", "../shared/data/src")]
    with pytest.raises(ValueError, match="no dataset.json"):
        prov.dataset_inputs(repo)


def test_the_check_finds_a_changed_a_missing_and_an_uncheckable_input(clone):
    repo, shared = clone
    pred = repo / "reports" / "pred.json"
    pred.write_text('{"a": 1}')
    (shared / "data" / "src" / "x").write_text("1")
    record = prov.provenance(
        [prov.file_input("predictions", pred), prov.file_input("source", shared / "data" / "src")], "cmd"
    )
    assert record["command"] == "cmd" and len(record["inputs"]) == 2
    assert [c.status for c in prov.check_record(record)] == ["ok", "ok"]
    pred.write_text('{"a": 2}')
    assert [c.status for c in prov.check_record(record)] == ["changed", "ok"]
    assert [c.status for c in prov.check_record(record, shared_present=False)] == ["changed", "unchecked"]
    pred.unlink()
    assert prov.check_record(record)[0].status == "missing"
    built = {"inputs": [{"role": "d", "kind": "built", "path": "data/x", "sha256": "0"}]}
    assert prov.check_record(built)[0].status == "unchecked"
    with pytest.raises(ValueError, match="unknown kind"):
        prov.check_record({"inputs": [{"role": "d", "kind": "elsewhere", "path": "x", "sha256": "0"}]})


def test_records_are_found_wherever_a_writer_put_them():
    doc = {"bandwidth": {}, "selection_study": {"provenance": {"commit": None, "inputs": []}}, "provenance": 3}
    assert [w for w, _ in prov.records(doc)] == ["/selection_study"]
