"""Build a dataset directory from a source: `hapticlink dataset build --source NAME --out DIR`."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path


def build(source: str, out: str | Path, path: str | Path | None = None, **options) -> Path:
    """Dispatch to the source's builder. Options are source-specific (see each builder)."""
    if path is not None and not Path(path).is_dir():  # each builder would name the first file it misses instead
        raise ValueError(f"--path {path}: no such folder")
    if source == "hatt-texnet":
        from models.offline.datasets.hatt_texnet import build_hatt

        if path is None:
            raise ValueError("--source hatt-texnet needs --path (e.g. ../shared/data/hatt-texnet)")
        return build_hatt(path, out, **options)
    if source == "synthetic":
        from models.offline.datasets.synthetic import build_synthetic

        return build_synthetic(out, **options)
    if source == "hassan2023":
        from models.offline.datasets.hassan2023 import build_hassan2023

        if path is None:
            raise ValueError("--source hassan2023 needs --path (e.g. ../shared/data/hassan2023)")
        return build_hassan2023(path, out, **options)
    if source == "recordings":
        from models.offline.datasets.recordings import build_recordings

        if path is None:
            raise ValueError("--source recordings needs --path to the folder of recordings")
        return build_recordings(path, out, **options)
    if source == "rosbag":
        from models.offline.datasets.recordings import build_recordings

        if path is None:
            raise ValueError(
                "--source rosbag needs --path to the folder of textures.csv and recordings/<texture>/ bags"
            )
        return _whole_or_nothing(out, lambda tmp: build_recordings(path, tmp, source="rosbag", **options))
    raise ValueError(f"unknown source {source!r}; expected hatt-texnet, hassan2023, synthetic, recordings or rosbag")


def _whole_or_nothing(out: str | Path, build_into: Callable[[Path], Path]) -> Path:
    """Build into a folder beside `out` and rename it to `out` once whole: a bag refused halfway leaves nothing."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--out {out}: exists and is not empty; name a new folder")
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        build_into(partial)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if out.exists():
        out.rmdir()
    partial.rename(out)
    return out
