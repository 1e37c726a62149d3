"""Read the Penn Haptic Texture Toolkit (HaTT) model and tap XML files.

HaTT files are read from a user-supplied path and never copied into the
repository (licence: non-profit research use, no redistribution).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel


def _values(node: ET.Element | None, what: str, path: Path) -> np.ndarray:
    if node is None:
        raise ValueError(f"{path}: missing <{what}>")
    try:
        return np.array([float(v.text or "") for v in node.findall("value")], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: <{what}> holds a value that is not a number") from None


def _scalar(root: ET.Element, tag: str, path: Path) -> float:
    node = root.find(tag)
    if node is None or node.text is None:
        raise ValueError(f"{path}: missing <{tag}>")
    try:
        return float(node.text)
    except ValueError:
        raise ValueError(f"{path}: <{tag}> is not a number: {node.text!r}") from None


def read_taps(path: str | Path) -> TapSet:
    """Parse a HaTT tap file: <tapSet><tap><tapSpeed/><tapAccel><value/>…"""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"{path}: cannot read tap XML: {exc}") from None
    taps = root.findall("tap")
    if not taps:
        raise ValueError(f"{path}: no <tap> elements")
    speeds = np.array([_scalar(t, "tapSpeed", path) for t in taps])
    traces = [_values(t.find("tapAccel"), "tapAccel", path) for t in taps]
    length = min(len(t) for t in traces)
    if length == 0:
        raise ValueError(f"{path}: a tap has no samples")
    return TapSet(speeds, np.stack([t[:length] for t in traces]))


def read_model(path: str | Path, taps_path: str | Path | None = None, name: str | None = None) -> VibrationModel:
    """Parse a HaTT model XML (<modelSet>) into a VibrationModel (triangles converted to 0-based)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"{path}: cannot read model XML: {exc}") from None
    rate = _scalar(root, "SampleRate", path)
    speeds = _values(root.find("speedList"), "speedList", path)
    forces = _values(root.find("forceList"), "forceList", path)
    tri_nodes = root.findall("tri")
    if not tri_nodes:
        raise ValueError(f"{path}: missing <tri>")
    tris = [_values(t, "tri", path) for t in tri_nodes]
    if any(len(t) != 3 for t in tris):
        raise ValueError(f"{path}: every <tri> must hold 3 vertex indices, got {sorted({len(t) for t in tris})}")
    if any(not np.all(t == np.round(t)) for t in tris):
        raise ValueError(f"{path}: <tri> holds a vertex index that is not an integer")
    triangles = np.array(tris, dtype=np.int64) - 1  # HaTT counts vertices from 1
    models = root.findall("model")
    if len(models) != len(speeds):
        raise ValueError(f"{path}: {len(models)} <model> elements but {len(speeds)} grid points")
    ar, ma, var, gain = [], [], [], []
    for node in models:
        ar.append(_values(node.find("ARlsf"), "ARlsf", path))
        ma.append(_values(node.find("MAlsf"), "MAlsf", path))
        var.append(_scalar(node, "var", path))
        gain.append(_scalar(node, "gain", path))
    for what, rows in (("ARlsf", ar), ("MAlsf", ma)):
        if len({len(r) for r in rows}) != 1:
            raise ValueError(f"{path}: {what} orders differ between grid points: {sorted({len(r) for r in rows})}")
    material = root.findtext("material") or path.stem
    return VibrationModel(
        name=name or path.stem,
        speeds=speeds,
        forces=forces,
        triangles=triangles,
        ar_lsf=np.array(ar),
        ma_lsf=np.array(ma),
        variance=np.array(var),
        gain=np.array(gain),
        mu=_scalar(root, "mu", path),
        max_speed=_scalar(root, "maxSpeed", path),
        max_force=_scalar(root, "maxForce", path),
        taps=read_taps(taps_path) if taps_path is not None else None,
        rate_hz=rate,
        provenance=(
            f"HaTT model '{material}' (Culbertson, Lopez Delgado, Kuchenbecker 2014); non-profit research use only"
        ),
    )
