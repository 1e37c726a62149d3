"""The CPU a run used: what an absolute time depends on, recorded beside it in every report."""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Any

#: the instruction-set flags that decide which kernels numpy, onnxruntime and numba run (an absolute time is only
#: comparable between hosts that share them)
ISA_FLAGS = ("avx2", "fma", "avx512f", "avx512bw", "avx512_vnni", "avx_vnni", "amx_int8")


def host(cpuinfo: str | Path = "/proc/cpuinfo") -> dict[str, Any]:
    """The CPU a run used, as `lscpu` names it: its model name and which of ISA_FLAGS it has (None where the
    file cannot be read, e.g. off Linux)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return {"model": platform.processor() or platform.machine(), "isa": None}
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() not in fields:
            fields[key.strip()] = value.strip()
    flags = set(fields.get("flags", "").split())
    return {
        "model": fields.get("model name") or platform.processor() or platform.machine(),
        "isa": [f for f in ISA_FLAGS if f in flags],
    }
