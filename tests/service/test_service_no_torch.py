"""Serving needs no torch: the app, the runtime (model, library, visual backbone) and a window's whole
pipeline run in a fresh interpreter without importing it."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_serving_path_imports_no_torch(visual_model, library_dir):
    script = textwrap.dedent(f"""
        import sys
        import numpy as np
        import service.app, service.commands, service.cli
        from service.app import create_app
        from service.cli import build_parser
        from service.pipeline import AdmittedBlock, SessionEstimator, SessionJob, estimate_batch
        from service.runtime import load_runtime
        from service.live_session import canonical_channels, stream_contract
        from service.settings import Settings
        from drivers.blocks import ChannelBlock, SampleBlock

        create_app(Settings())
        build_parser()
        rt = load_runtime(Settings(model_path={str(visual_model.model)!r}, library_dir={str(library_dir)!r},
                                   backbone_path={str(visual_model.backbone)!r}))
        image = open({str(library_dir / "images" / "synth_000.png")!r}, "rb").read()
        visual = rt.embed_frame(rt.decode_frame(image))
        contract = stream_contract(rt, Settings())
        est = SessionEstimator(rt, contract, alpha=0.5, steadiness_windows=5, top_k=3, hysteresis_margin=5,
                               hysteresis_hold=2)
        rng = np.random.default_rng(0)
        accel = rng.standard_normal((600, 3)).astype(np.float32)
        block = SampleBlock(0.0, {{"accel": ChannelBlock(accel, 1000.0, "m/s^2"),
                                  "force": ChannelBlock(np.full(600, 1.5, np.float32), 1000.0, "N"),
                                  "speed": ChannelBlock(np.full(600, 80.0, np.float32), 1000.0, "mm/s")}}, 0)
        adv = contract.admit(contract.start(), canonical_channels(block), block.t0)
        admitted = AdmittedBlock(0, adv.cursor.segment, adv.cursor.origin_t0, adv.channels, adv.windows_after, 0)
        # what the batcher runs
        (result,) = estimate_batch(rt, [SessionJob(est, [admitted], visual, adv.windows_added)])
        assert result.error is None and len(result.estimates) == 1, result
        leaked = sorted(m for m in sys.modules if m == "torch" or m.startswith("torch."))
        print("LEAKED" if leaked else "CLEAN", leaked[:5])
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "CLEAN" in out.stdout, out.stdout
