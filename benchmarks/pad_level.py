"""How loud the console's touch pad plays a typical stroke, per texture, at a full scale.

`python -m benchmarks.pad_level [--hatt-source DIR] [--full-scale 10]`

The stroke: what a mouse does on the pad — back and forth along x at 159 mm/s (600 CSS px/s), turning every 0.4 s,
1 N (the pad's default force), its position smoothed by the worklet's two 15 ms one-pole stages and its speed
taken from that position. Each texture of the synthetic world (24, bumps included) and of HaTT–TexNet (100, when at
hand; they have no bumps) is rendered along it by the operator's renderer (texture_library.renderer.render_stroke,
as the worklet renders it, seeded excitation) and measured as the pad measures it: the largest RMS over 100 ms
(after the first 0.2 s), in dBFS at the full scale (m/s² = ±1); and whether any sample clips. The same stroke is
also rendered by the world's `synthesis.render` (direct form I) to show its turnaround bursts. Writes
reports/bench/pad_level.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report
from models.offline.provenance import file_input
from texture_library.procedural import make_world
from texture_library.renderer import render_stroke
from texture_library.synthesis import render
from texture_library.vibration import VibrationModel

DEFAULT_HATT = Path("../shared/data/hatt-texnet")
OUT = Path("reports/bench/pad_level.json")
STROKE_MM_S = 159.0
TURN_S = 0.4
SMOOTHING_MS = 15.0


def pad_stroke(seconds: float = 1.2, rate_hz: float = 1000.0) -> tuple[np.ndarray, np.ndarray]:
    """(speed (n,) mm/s, position (n,) mm) of a mouse stroking back and forth, smoothed as the worklet smooths it."""
    n = int(seconds * rate_hz)
    phase = (np.arange(n) / rate_hz % (2 * TURN_S)) / (2 * TURN_S)
    target = np.where(phase < 0.5, 2 * phase, 2 - 2 * phase) * STROKE_MM_S * TURN_S
    alpha = 1 - np.exp(-1000.0 / (rate_hz * SMOOTHING_MS))
    p1, x = np.empty(n), np.empty(n)
    p1[0] = x[0] = target[0]
    for i in range(1, n):
        p1[i] = p1[i - 1] + alpha * (target[i] - p1[i - 1])
        x[i] = x[i - 1] + alpha * (p1[i] - x[i - 1])
    return np.abs(np.gradient(x)) * rate_hz, x


def level(model: VibrationModel, full_scale: float, seed: int = 0) -> dict:
    speed, x = pad_stroke()
    n = speed.size
    e = np.random.default_rng(seed).standard_normal(n)
    force = np.ones(n)
    y = render_stroke(model, speed, force, excitation=e, position=x)
    blocks = y[200:].reshape(-1, 100)
    peak_rms = float(np.sqrt((blocks**2).mean(axis=1)).max())
    direct = render(model, speed, force, excitation=e)
    return {
        "texture": model.name,
        "peak_dbfs": round(20 * np.log10(max(peak_rms, 1e-12) / full_scale), 1),
        "clips": bool(np.abs(y).max() > full_scale),
        "peak_abs_m_s2": round(float(np.abs(y).max()), 3),
        "direct_form_peak_abs_m_s2": round(float(np.abs(direct).max()), 3),
    }


def summary(rows: list[dict]) -> dict:
    db = np.array([r["peak_dbfs"] for r in rows])
    burst = np.array([r["direct_form_peak_abs_m_s2"] / max(r["peak_abs_m_s2"], 1e-12) for r in rows])
    return {
        "textures": len(rows),
        "median_peak_dbfs": round(float(np.median(db)), 1),
        "p10_p90_peak_dbfs": [round(float(v), 1) for v in np.percentile(db, [10, 90])],
        "share_in_minus20_minus6": round(float(np.mean((db >= -20) & (db <= -6))), 2),
        "share_clipping": round(float(np.mean([r["clips"] for r in rows])), 2),
        "direct_form_bursts_over_3x": int(np.sum(burst > 3)),
        "direct_form_worst_ratio": round(float(burst.max()), 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hatt-source", type=Path, default=DEFAULT_HATT, help="HaTT–TexNet folder (models/*.xml)")
    ap.add_argument("--full-scale", type=float, default=10.0, help="m/s² = ±1 (the console's default)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    worlds = {"synthetic": [t.model for t in make_world(24, 0, image_size=32)]}
    hatt = sorted((args.hatt_source / "models").glob("*.xml")) if args.hatt_source else []
    if hatt:
        from texture_library.hatt_xml import read_model

        worlds["hatt-texnet"] = [read_model(p) for p in hatt]
    doc: dict = {
        "command": "python -m benchmarks.pad_level " + " ".join(argv if argv is not None else sys.argv[1:]),
        "stroke": f"back and forth at {STROKE_MM_S} mm/s, turning every {TURN_S} s, 1 N, 1.2 s",
        "full_scale_m_s2": args.full_scale,
        "target_peak_dbfs": [-20, -6],
    }
    for name, models in worlds.items():
        rows = [level(m, args.full_scale) for m in models]
        doc[name] = {"summary": summary(rows), "rows": rows}
        print(name, doc[name]["summary"], flush=True)
    write_report(args.out, doc, [file_input("HaTT models", args.hatt_source / "models")] if hatt else ())
    print(f"wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
