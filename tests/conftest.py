"""Suite-wide settings: property tests draw the same examples on every run (fixed seeds), so a
green run on one machine is green on CI and a failure reproduces. No example has a deadline, and slow
data generation is no failure: a host busy with other work makes both slow, and neither says anything
about the code (speed is measured in benchmarks/).

`built_once` builds a session's expensive artefacts (datasets, trained models, demo assets) once per run,
however many pytest-xdist workers need them (`make test` runs two)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock
from hypothesis import HealthCheck, settings

settings.register_profile("fixed-seed", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("fixed-seed")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The files that hold a test marked `slow` run first, each file's tests in their order: `make test`'s workers
    take whole files in this order (`--dist loadfile --no-loadscope-reorder`), so the long files start at once and
    the short ones fill in around them, instead of a worker starting a two-minute file when the other has run out."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: the order within each group is kept


class BuiltOnce:
    """Folders filled once per test run, shared by every worker of that run.

    `folder(name, fill)` returns the run's folder for `name`, calling fill(folder) on an empty one first if no
    worker has yet; a worker that asks while another fills it waits for it (a file lock). The artefacts are
    deterministic builds (fixed seeds), so every worker reads what it would have built itself. A fill that
    raises leaves no folder marked built: the next worker to ask tries again (and fails the same way)."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def folder(self, name: str, fill: Callable[[Path], object]) -> Path:
        folder = self.root / f"built-{name}"
        done = folder / ".built"
        with FileLock(f"{folder}.lock"):
            if not done.is_file():
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir(parents=True)
                fill(folder)
                done.touch()
        return folder


@pytest.fixture(scope="session")
def built_once(tmp_path_factory) -> BuiltOnce:
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # a worker's base temp is popen-gwN inside the run's: that one is shared
    return BuiltOnce(root)


@pytest.fixture(scope="session")
def demo_small_assets(built_once):
    """`hapticlink demo`'s assets at a small size (5 textures, 2 probes): dataset, models, library, probes."""
    from demo.assets import prepare_assets
    from demo.run import DemoAssets

    def fill(folder: Path) -> None:
        assets = prepare_assets(folder / "assets", n_textures=5, n_probes=2)
        (folder / "paths.json").write_text(json.dumps([str(p) for p in dataclasses.astuple(assets)]))

    folder = built_once.folder("demo-assets", fill)
    return DemoAssets(*map(Path, json.loads((folder / "paths.json").read_text())))
