"""Time to build the HaTT–TexNet dataset, stage by stage: `python -m benchmarks.dataset_build`.

Builds into a temporary folder (or --out) from ../shared/data/hatt-texnet and writes
reports/bench/dataset_build.json. The visual stage uses a fresh feature cache so every
image view really goes through the backbone.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.report_file import write_report
from models.offline.datasets.check import check_dataset
from models.offline.datasets.hatt_texnet import build_hatt
from models.offline.featurize import tactile_table, visual_table

OUT = Path("reports/bench/dataset_build.json")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--src", default="../shared/data/hatt-texnet")
    p.add_argument("--out", help="dataset folder (default: a temporary one)")
    p.add_argument("--limit", type=int, help="only the first N textures")
    args = p.parse_args(argv)
    if not Path(args.src).is_dir():
        print(f"no HaTT–TexNet data at {args.src}; nothing to time", file=sys.stderr)
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or Path(tmp) / "hatt-texnet")
        os.environ["HAPTICLINK_CACHE"] = str(Path(tmp) / "cache")  # cold feature cache: every view is embedded
        stages = {}
        t0 = time.perf_counter()
        build_hatt(args.src, out, limit=args.limit)
        stages["render_recordings_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        tact = tactile_table(out)
        stages["tactile_features_s"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        vis = visual_table(out)
        stages["visual_features_s"] = time.perf_counter() - t2
        t3 = time.perf_counter()
        problems = check_dataset(out)
        stages["check_s"] = time.perf_counter() - t3
    result = {
        "textures": len(tact.textures),
        "windows": int(tact.X.shape[0]),
        "image_views": int(vis.X.shape[0] * vis.X.shape[1]),
        "backbone": vis.backbone,
        "stages": {k: round(v, 1) for k, v in stages.items()},
        "total_s": round(sum(stages.values()), 1),
        "check_problems": len(problems),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "python": platform.python_version()},
        "command": "python -m benchmarks.dataset_build" + (f" --limit {args.limit}" if args.limit else ""),
    }
    print(json.dumps(result, indent=1))
    if args.limit is None:
        write_report(OUT, result)
    return result


if __name__ == "__main__":
    main()
