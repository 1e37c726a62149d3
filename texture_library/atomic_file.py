"""Files replaced whole or not at all: write a temporary file beside the target, then rename it over the target.

A rename within one directory is atomic, so a reader (another process, another replica) sees the old file
or the whole new one, never a half-written one, and a crash leaves no partial target behind. The one home
of this idea for every layer (the library, the feature caches, the studies' results); it lives at the
bottom layer so that each of them may import it.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A fresh temporary path beside `path`, to be written inside the block; renamed onto `path` when the
    block ends, removed when it raises. The temporary name keeps `path`'s suffix (np.savez appends ".npz"
    to a name without it) and is hidden and unique (process id and a random part), so concurrent writers
    never share one. The parent folder is created when missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path: str | Path, data: bytes) -> Path:
    """`data` as the whole content of `path`, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """`text` (UTF-8) as the whole content of `path`, atomically."""
    return write_bytes(path, text.encode("utf-8"))
