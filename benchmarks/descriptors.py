"""Per-frame cost of each texture descriptor (models/visual/descriptors.py) on CPU, one thread.

    python -m benchmarks.descriptors [--repeats 5] [--image PATH] [--out reports/bench/descriptors.json]

One frame: a 1024×1024 image (a seeded synthetic texture, or --image, loaded in colour), as
`visual_features` sees it — each descriptor times its own work, including the zoom to its size
(`VisualConfig.descriptor_size`, `scattering_size`); the floor measured in the same run is the
GLCM the default visual vector already pays (glcm_features on the full frame). The first
scattering call builds kymatio's filter bank (seconds); it is timed apart, as `scattering_setup`.
Median of `repeats` calls after one warm-up.
"""

from __future__ import annotations

import argparse
import os
import platform
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report
from benchmarks.visual import benchmark_image, summarise, time_call
from models.offline.provenance import file_input

DEFAULT_OUT = Path("reports") / "bench" / "descriptors.json"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--image")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(DEFAULT_OUT))
    args = p.parse_args(argv)
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    import time

    from models.visual.config import VisualConfig
    from models.visual.descriptors import (
        colour_statistics,
        grid_statistics,
        lbp_histograms,
        radial_power_spectrum,
        scattering_features,
        zoom_to,
    )
    from models.visual.glcm import glcm_features
    from models.visual.image import load_colour

    cfg = VisualConfig(descriptors=("lbp", "spectrum", "colour", "grids", "scattering"))
    if args.image:
        colour = load_colour(args.image)
        gray = colour @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    else:
        gray = benchmark_image(None, args.seed)
        colour = np.repeat(gray[..., None], 3, axis=2)
    t0 = time.perf_counter()
    scattering_features(zoom_to(gray, cfg.scattering_size), cfg.scattering_j, cfg.scattering_l)
    setup_s = time.perf_counter() - t0
    d = cfg.descriptor_size
    calls = {
        "glcm (floor: already in every visual vector)": lambda: glcm_features(gray, 16, (1,), (0.0, 45.0, 90.0, 135.0)),
        "lbp": lambda: lbp_histograms(zoom_to(gray, d), cfg.lbp_radii),
        "spectrum": lambda: radial_power_spectrum(zoom_to(gray, d), cfg.spectrum_bands),
        "colour": lambda: colour_statistics(np.stack([zoom_to(colour[..., c], d) for c in range(3)], axis=2)),
        "grids": lambda: grid_statistics(zoom_to(gray, d), cfg.grid_scales),
        "scattering": lambda: scattering_features(
            zoom_to(gray, cfg.scattering_size), cfg.scattering_j, cfg.scattering_l
        ),
    }
    results = {name: summarise(time_call(fn, args.repeats)) for name, fn in calls.items()}
    floor = results["glcm (floor: already in every visual vector)"]["median_ms"]
    total = sum(v["median_ms"] for k, v in results.items() if not k.startswith("glcm"))
    out = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg(),
        "threads": 1,
        "image": args.image or "synthetic 1024×1024",
        "descriptor_size": d,
        "scattering_setup_s": setup_s,
        "per_descriptor": results,
        "all_descriptors_median_ms": total,
        "ratio_all_to_glcm_floor": total / floor,
    }
    write_report(args.out, out, [file_input("image", args.image)] if args.image else ())
    print(f"per frame, 1 thread (load average {os.getloadavg()[0]:.1f}):")
    for name, r in results.items():
        print(f"  {name:45s} {r['median_ms']:8.1f} ms")
    print(f"  all descriptors {total:.1f} ms = {total / floor:.1f} × the GLCM floor; scattering setup {setup_s:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
