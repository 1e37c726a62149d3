"""The serving side of intervals and OOD flags runs on numpy alone: no torch, no scikit-learn."""

import subprocess
import sys
import textwrap


def test_intervals_and_detector_from_json_import_neither_torch_nor_sklearn():
    script = textwrap.dedent("""
        import json, sys
        import numpy as np
        from models.inference.intervals import IntervalCalibration, EmaUncertainty, calibrations_from_card
        from models.inference.ood import OODDetector
        rng = np.random.default_rng(0)
        det = OODDetector.fit([rng.normal(size=(20, 30)) for _ in range(6)], rng.normal(size=(6, 2, 10)))
        truth = rng.normal(size=(60, 4)) * 20
        cal = IntervalCalibration.fit(truth + rng.normal(size=(60, 4)), truth, prior_ratings=truth)
        card = {"intervals": {"window": cal.to_dict()}, "ood": det.to_dict()}
        card = json.loads(json.dumps(card))  # what the ONNX metadata holds
        cals = calibrations_from_card(card["intervals"])
        det = OODDetector.from_dict(card["ood"])
        frame = det.check_visual(rng.normal(size=10))
        res = det.check(rng.normal(size=(3, 30)), frame=frame)
        lo, hi = cals["window"].interval(rng.normal(size=(3, 4)), None, 0.9, ood=res.flags)
        EmaUncertainty(0.5).update(bool(res.flags[0]), float(res.distance[0]))
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "sklearn"))
        print("LEAKED" if leaked else "CLEAN", leaked[:5])
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("CLEAN"), out.stdout
