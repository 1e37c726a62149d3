"""One file format for hapticlink's arrays: a NumPy .npz whose `header` member is a JSON object.

The header names the format and its version; readers refuse files of another format or a
version they do not know, and every failure is a ValueError naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: the most a file may hold once decompressed (the declared sizes of its members, read before any is inflated): a
#: few kB of zeros can declare gigabytes, and a recording an hour long at 1 kHz is 0.1 GB
MAX_NPZ_BYTES = 1 << 30


def save_npz(path: str | Path, fmt: str, version: int, header: dict, arrays: dict[str, np.ndarray]) -> Path:
    path = Path(path)
    doc = {"format": fmt, "version": version, **header}
    np.savez_compressed(path, allow_pickle=False, header=np.array(json.dumps(doc)), **arrays)
    return path


def load_npz(path: str | Path, fmt: str, version: int) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) of a file written by save_npz with this format and version."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{fmt} file not found: {path}")
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same problem to the user
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    with z:
        declared = sum(info.file_size for info in z.zip.infolist())
        if declared > MAX_NPZ_BYTES:
            raise ValueError(
                f"{path}: holds {declared / 2**20:.0f} MiB once decompressed; at most {MAX_NPZ_BYTES / 2**20:.0f} MiB "
                "are read"
            )
        if "header" not in z:
            raise ValueError(f"{path}: no header (not a {fmt} file)")
        try:
            header = json.loads(str(z["header"]))
        except ValueError as exc:
            raise ValueError(f"{path}: header is not valid JSON ({exc})") from None
        if not isinstance(header, dict):
            raise ValueError(f"{path}: header must be a JSON object")
        if header.get("format") != fmt:
            raise ValueError(f"{path}: format is {header.get('format')!r}, expected {fmt!r}")
        if header.get("version") != version:
            raise ValueError(
                f"{path}: unsupported {fmt} version {header.get('version')!r} (this hapticlink reads {version})"
            )
        try:
            arrays = {k: z[k] for k in z.files if k != "header"}
        except Exception as exc:  # noqa: BLE001 - a corrupt member (bad zip, bad zlib stream)
            raise ValueError(f"{path}: cannot read arrays ({exc})") from None
    return header, arrays
