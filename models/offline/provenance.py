"""What a report was made from: the SHA-256 of every input it read and the commit of the code that wrote it.

Every writer of a report JSON under reports/ stores `provenance(...)` under a `provenance` key, and
tests/reports/test_report_inputs.py checks each committed report against its inputs. An input is one of:

- `repo`: a file in this repository (a committed predictions file, a study's JSON): checkable everywhere;
- `shared`: the licensed source data in ../shared beside the repository (a file, or a folder hashed as a
  tree: the sorted relative paths with each file's SHA-256): checkable where ../shared is present;
- `built`: a file made from them on one machine (a dataset's `dataset.json` under data/, a model file under
  artifacts/): recorded, but not checkable on a fresh clone or in CI, since nothing of it is committed. A built
  dataset also names its source (`shared`, or none: the synthetic world is generated from code and a seed).

Paths are stored relative to the repository root (../shared/… for the shared data), so the record reads the same
on every clone.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: the repository root (this file is models/offline/provenance.py)
REPO_ROOT = Path(__file__).resolve().parents[2]
#: where the licensed data lives, beside the repository
SHARED_ROOT = REPO_ROOT.parent / "shared"
KINDS = ("repo", "shared", "built")
#: git-ignored folders of the repository whose files are made on one machine (datasets, models, feature caches)
BUILT_DIRS = ("data", "artifacts", "cache")
_CHUNK = 1 << 20


def file_sha256(path: str | Path) -> str:
    """SHA-256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def tree_sha256(folder: str | Path) -> str:
    """SHA-256 over every file below `folder`: one line `relative/path<TAB>file sha256` per file, sorted by path.
    Names and contents count; timestamps and permissions do not."""
    root = Path(folder)
    lines = [f"{p.relative_to(root).as_posix()}\t{file_sha256(p)}\n" for p in sorted(root.rglob("*")) if p.is_file()]
    if not lines:
        raise ValueError(f"{root}: no files to hash")
    return hashlib.sha256("".join(lines).encode()).hexdigest()


def path_sha256(path: str | Path) -> str:
    """`file_sha256` of a file, `tree_sha256` of a folder."""
    p = Path(path)
    if p.is_dir():
        return tree_sha256(p)
    if p.is_file():
        return file_sha256(p)
    raise ValueError(f"{p}: no such file or folder to hash")


def _inside(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


def locate(path: str | Path) -> tuple[str, str]:
    """(kind, stored path) of an input: `repo` for a file the repository tracks or could (outside BUILT_DIRS),
    `shared` below ../shared, `built` otherwise. Stored paths are relative to the repository root."""
    p = Path(os.path.abspath(path))  # a link under data/ to a dataset built elsewhere keeps its data/ name
    if _inside(p, REPO_ROOT):
        rel = p.relative_to(REPO_ROOT)
        built = rel.parts[0] in BUILT_DIRS
        return ("built" if built else "repo"), rel.as_posix()
    real, shared = p.resolve(), SHARED_ROOT.resolve()
    if _inside(real, shared):
        return "shared", (Path("../shared") / real.relative_to(shared)).as_posix()
    return "built", p.as_posix()


def resolve(stored: str) -> Path:
    """The file a stored path names on this clone."""
    return (REPO_ROOT / stored).resolve() if not Path(stored).is_absolute() else Path(stored)


@dataclass(frozen=True)
class Input:
    """One input a report read: its role (`predictions`, `dataset`, `model`, …), where it lives, its digest."""

    role: str
    kind: str
    path: str
    sha256: str

    def to_dict(self) -> dict[str, str]:
        return {"role": self.role, "kind": self.kind, "path": self.path, "sha256": self.sha256}


def file_input(role: str, path: str | Path) -> Input:
    """An input file (or folder) as it is now."""
    kind, stored = locate(path)
    return Input(role, kind, stored, path_sha256(path))


def dataset_inputs(dataset: str | Path, role: str = "dataset") -> list[Input]:
    """A built dataset: its manifest (`built`) and, when it was built from files in ../shared, that source folder
    (`shared`, hashed as a tree). A synthetic dataset has no source: its manifest records the generator's seed."""
    root = Path(dataset)
    manifest = root / "dataset.json"
    if not manifest.is_file():
        raise ValueError(f"{root}: no dataset.json (not a hapticlink dataset)")
    out = [file_input(f"{role} manifest", manifest)]
    src = json.loads(manifest.read_text()).get("build", {}).get("src")
    if src:
        source = _shared_source(Path(src))
        if source is not None:
            out.append(file_input(f"{role} source", source))
    return out


def _shared_source(src: Path) -> Path | None:
    """A dataset's recorded source folder on this clone: the path itself, or the same `shared/…` tail under
    ../shared (a dataset built on another checkout names that checkout's absolute path)."""
    if src.is_dir():
        return src
    parts = src.parts
    if "shared" in parts:
        tail = Path(*parts[parts.index("shared") + 1 :])
        candidate = SHARED_ROOT / tail
        if candidate.is_dir():
            return candidate
    return None


def git_commit() -> dict[str, Any]:
    """The commit the writing code came from and whether the tree had uncommitted changes outside reports/ (None:
    no git here)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            # the reports a run rewrites are not the code that ran: only changes outside reports/ make it dirty
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)reports"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}
    return {"commit": head, "dirty": bool(status.strip())}


def provenance(inputs: Iterable[Input], command: str | None = None) -> dict[str, Any]:
    """The `provenance` record of a report: the commit that wrote it, the command, each input's digest."""
    return {**git_commit(), "command": command, "inputs": [i.to_dict() for i in inputs]}


def records(doc: Any, where: str = "") -> list[tuple[str, dict]]:
    """Every `provenance` record inside a report JSON (a report shared by several writers holds one per writer),
    with the key path that leads to it."""
    found: list[tuple[str, dict]] = []
    if isinstance(doc, Mapping):
        for key, value in doc.items():
            if key == "provenance" and isinstance(value, Mapping) and "inputs" in value:
                found.append((where or "/", dict(value)))
            else:
                found.extend(records(value, f"{where}/{key}"))
    elif isinstance(doc, list):
        for k, value in enumerate(doc):
            found.extend(records(value, f"{where}/{k}"))
    return found


@dataclass(frozen=True)
class Check:
    """One input of one report checked on this clone: `ok`, `changed`, `missing` (a repo input gone) or `unchecked`
    (a built input, or ../shared absent) with the reason."""

    path: str
    kind: str
    status: str
    why: str = ""


def check_record(record: Mapping[str, Any], shared_present: bool | None = None) -> list[Check]:
    """Check each input of one provenance record against the files on this clone."""
    have_shared = SHARED_ROOT.is_dir() if shared_present is None else shared_present
    out = []
    for item in record["inputs"]:
        kind, stored, want = item["kind"], item["path"], item["sha256"]
        if kind not in KINDS:
            raise ValueError(f"input {stored!r}: unknown kind {kind!r} (one of {KINDS})")
        if kind == "built":
            out.append(Check(stored, kind, "unchecked", "built on one machine, not committed"))
            continue
        if kind == "shared" and not have_shared:
            out.append(Check(stored, kind, "unchecked", "../shared is not present"))
            continue
        path = resolve(stored)
        if not path.exists():
            out.append(Check(stored, kind, "missing", f"{path} is gone"))
            continue
        got = path_sha256(path)
        out.append(Check(stored, kind, "ok" if got == want else "changed", "" if got == want else f"now {got[:12]}"))
    return out
