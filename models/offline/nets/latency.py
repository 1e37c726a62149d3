"""Per-window cost of a network: onnxruntime latency at batch 1 and parameter count.

No torch import: `onnx_latency` runs on onnxruntime alone, `param_count` only walks
``model.parameters()``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

WARMUP_RUNS = 20


def _input_feed(session: ort.InferenceSession, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One random float32 row per graph input; the batch axis (symbolic or not) is 1."""
    feed = {}
    for spec in session.get_inputs():
        dims = spec.shape[1:]
        if not all(isinstance(d, int) for d in dims):
            raise ValueError(f"input {spec.name} has non-static feature dims {spec.shape}")
        feed[spec.name] = rng.standard_normal((1, *dims)).astype(np.float32)
    return feed


def onnx_latency(path: str | Path, n: int = 200, threads: int = 1) -> dict[str, float]:
    """Latency of one window (batch 1) through the ONNX model at ``path``.

    onnxruntime CPU EP, intra_op_num_threads=threads, inter_op_num_threads=1, sequential
    execution; WARMUP_RUNS untimed runs first, then ``n`` timed ones.
    Returns {"p50_us", "p90_us", "mean_us"} in microseconds.
    """
    if n < 1 or threads < 1:
        raise ValueError(f"onnx_latency needs n ≥ 1 and threads ≥ 1, got n={n}, threads={threads}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    feed = _input_feed(session, np.random.default_rng(0))
    return call_latency(lambda: session.run(None, feed), n=n, warmup=WARMUP_RUNS)


def call_latency(call: Callable[[], Any], n: int, warmup: int) -> dict[str, float]:
    """`warmup` untimed calls, then `n` timed ones → {"p50_us", "p90_us", "mean_us"} in microseconds."""
    for _ in range(warmup):
        call()
    times = np.empty(n)
    for k in range(n):
        t0 = time.perf_counter_ns()
        call()
        times[k] = (time.perf_counter_ns() - t0) / 1e3
    return {
        "p50_us": float(np.percentile(times, 50)),
        "p90_us": float(np.percentile(times, 90)),
        "mean_us": float(times.mean()),
    }


def param_count(model: Any, trainable_only: bool = False) -> int:
    """Number of parameters of a torch module (all, or only those requiring grad)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)
