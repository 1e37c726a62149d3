"""Warm-up: run every piece of the serving path once before /ready says ready, so no window pays for it.

What the first real window would otherwise pay: onnxruntime's lazy initialisation (per model and
batch shape), the visual backbone on a full frame's patch grid (not one patch), numpy/scipy code
paths of the preprocessor and `window_features` (first calls allocate and import), and, after
start-up, a full garbage collection of everything loading created (the probe saw a 67 ms one on the
pool thread). `warm_up` runs a synthetic stream through the real pipeline — admission contract,
preprocessor, features, every model, lookup — for a tactile and (where the model reads images) a
tactile+visual session; the caller then freezes the start-up heap (`gc.freeze()`), so later
collections do not walk it.
"""

from __future__ import annotations

import gc
import time

import numpy as np

from models.tactile.taps import tap_features
from service.live_session import stream_contract
from service.pipeline import AdmittedBlock, SessionEstimator, SessionJob, estimate_batch
from service.runtime import Runtime
from service.settings import Settings
from texture_library.recording import Channel

WARM_UP_FRAME_PX = 448  # a camera frame: the backbone runs on its whole patch grid
WARM_UP_WINDOWS = 4


def warm_up(runtime: Runtime, settings: Settings, seed: int = 0) -> float:
    """Run the serving path on synthetic input; returns the seconds it took. Raises what the path raises."""
    started = time.perf_counter()
    rng = np.random.default_rng(seed)
    visual, checks = None, {}
    if runtime.backbone is not None:
        frame = rng.uniform(0, 1, size=(WARM_UP_FRAME_PX, WARM_UP_FRAME_PX)).astype(np.float32)
        visual, reasons = runtime.embed_and_inspect(frame)
        checks = runtime.frame_checks(reasons, visual)
    contract = stream_contract(runtime, settings)
    inputs = [None] + ([visual] if visual is not None else [])
    if runtime.needs_visual and runtime.tactile is None:
        inputs = inputs[1:]  # no tactile-only model: windows are only ever estimated with an embedding
    for batch_sessions in (1, 3):  # one session alone, and a batch of several (other array shapes)
        jobs = [
            synthetic_job(runtime, settings, contract, rng, v, checks if v is not None else {})
            for v in inputs
            for _ in range(batch_sessions)
        ]
        for result in estimate_batch(runtime, jobs):
            if result.error is not None:
                raise result.error
    for model in runtime.served_models():  # the adaptive policy may not have needed every model above
        model.predictor.warm_up()
    gc.collect()
    return time.perf_counter() - started


def synthetic_job(
    runtime: Runtime, settings: Settings, contract, rng: np.random.Generator, visual, checks: dict
) -> SessionJob:
    """A fresh session's job of WARM_UP_WINDOWS windows of random vibration at constant speed and force
    (warm-up, and benchmarks.uncertainty's per-window cost)."""
    rate = runtime.tactile_config.rate_hz
    n = int(round(rate * (runtime.tactile_config.window_s + (WARM_UP_WINDOWS - 1) * runtime.tactile_config.hop_s)))
    # 3-column force (tangential x, y, normal): what a friction model needs, and what the others take the normal of
    force = np.column_stack([np.full(n, 0.45), np.zeros(n), np.full(n, 1.5)])
    channels = {
        "accel": Channel(rng.normal(0, 1, size=(n, 3)), rate),
        "force": Channel(force, rate),
        "speed": Channel(np.full(n, 80.0), rate),
    }
    est = SessionEstimator.from_settings(runtime, contract, settings)
    adv = contract.advance(contract.start(), channels, 0.0)
    taps = None
    if runtime.needs_taps:  # a model with tap features: the tap function runs once too
        ringing = np.exp(-np.arange(100) / 8.0) * np.sin(np.arange(100) * 0.9)
        taps = tap_features(
            np.array([20.0, 40.0]), np.stack([20.0 * ringing, 40.0 * ringing]) + rng.normal(0, 0.05, (2, 100))
        )
    block = AdmittedBlock(
        0, adv.cursor.segment, adv.cursor.origin_t0, adv.channels, adv.windows_after, time.perf_counter_ns(), taps
    )
    return SessionJob(est, [block], visual, adv.windows_added, checks)
