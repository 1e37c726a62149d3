"""Latency measurement and parameter counting (no timing thresholds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from torch import nn

from models.offline.nets import presets
from models.offline.nets.export import export_onnx
from models.offline.nets.latency import onnx_latency, param_count


def test_param_count() -> None:
    net = nn.Sequential(nn.Linear(3, 2), nn.Linear(2, 5))
    assert param_count(net) == 3 * 2 + 2 + 2 * 5 + 5
    net[0].weight.requires_grad_(False)
    assert param_count(net, trainable_only=True) == 2 + 2 * 5 + 5


@pytest.mark.parametrize("name", ["vtnet-tactile", "vision-1dcnn"])  # one input each
def test_onnx_latency_reports_percentiles(name: str, tmp_path: Path) -> None:
    f, d = 526, 64
    ones = {"tactile_mean": np.zeros(f), "tactile_std": np.ones(f), "visual_mean": np.zeros(d),
            "visual_std": np.ones(d), "target_mean": np.zeros(4), "target_std": np.ones(4)}  # fmt: skip
    path = export_onnx(presets.build(name, d, f, seed=0), tmp_path / "m.onnx", **ones, metadata={})
    result = onnx_latency(path, n=10, threads=1)
    assert set(result) == {"p50_us", "p90_us", "mean_us"}
    assert 0 < result["p50_us"] <= result["p90_us"]
    assert result["mean_us"] > 0


def test_bad_arguments_raise(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="n ≥ 1"):
        onnx_latency(tmp_path / "missing.onnx", n=0)
