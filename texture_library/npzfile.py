"""One file format for hapticlink's arrays: a NumPy .npz whose `header` member is a JSON object.

The header names the format and its version; readers refuse files of another format or a
version they do not know, and every failure is a ValueError naming the file.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

#: the most a file may hold once decompressed (the declared sizes of its members, read before any is inflated): a
#: few kB of zeros can declare gigabytes, and a recording an hour long at 1 kHz is 0.1 GB
MAX_NPZ_BYTES = 1 << 30


def _size(nbytes: int) -> str:
    # bytes, so that a file one byte over the limit never reads as the limit itself
    return f"{nbytes:,} bytes ({nbytes / 2**20:.1f} MiB)"


def _check_size(path: Path, nbytes: int, *, writing: bool) -> None:
    """One limit, counted the same way, for writing and reading: save_npz never writes what load_npz refuses."""
    if nbytes > MAX_NPZ_BYTES:
        verb, outcome = ("would hold", ", so it is not written") if writing else ("holds", "")
        raise ValueError(
            f"{path}: {verb} {_size(nbytes)} once decompressed; at most {_size(MAX_NPZ_BYTES)} are read{outcome}"
        )


def _member_size(array: np.ndarray) -> int:
    """What a member of np.savez declares as its size: its .npy header, then its data."""
    array = np.asanyarray(array)
    d = np.lib.format.header_data_from_array_1_0(array)
    buf = io.BytesIO()
    try:
        np.lib.format.write_array_header_1_0(buf, d)
    except ValueError:  # a header past 64 KiB: np.save falls back to format 2.0 too
        buf = io.BytesIO()
        np.lib.format.write_array_header_2_0(buf, d)
    return buf.tell() + array.nbytes


def save_npz(path: str | Path, fmt: str, version: int, header: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write the file; ValueError (nothing written) if load_npz would refuse it for its size."""
    path = Path(path)
    doc = {"format": fmt, "version": version, **header}
    header_array = np.array(json.dumps(doc))
    _check_size(path, _member_size(header_array) + sum(_member_size(a) for a in arrays.values()), writing=True)
    np.savez_compressed(path, allow_pickle=False, header=header_array, **arrays)
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
        _check_size(path, sum(info.file_size for info in z.zip.infolist()), writing=False)
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
