"""Speed against accuracy: LOOCV mean MAE vs per-window latency, the Pareto frontier marked."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def pareto_front(latency: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Boolean mask of points no other point beats in both latency and error (ties kept)."""
    latency, error = np.asarray(latency, float), np.asarray(error, float)
    if latency.shape != error.shape or latency.ndim != 1:
        raise ValueError(f"latency and error must be 1-D of equal length, got {latency.shape} and {error.shape}")
    keep = np.ones(latency.size, bool)
    for i in range(latency.size):
        dominated = (latency <= latency[i]) & (error <= error[i]) & ((latency < latency[i]) | (error < error[i]))
        keep[i] = not dominated.any()
    return keep


def speed_accuracy_chart(rows: list[dict], path: Path, *, reference: dict[str, float] | None = None) -> Path:
    """rows: {"model", "mae", "latency_us", "n_params", "runtime"}; reference: horizontal lines (label → MAE)."""
    lat = np.array([r["latency_us"] for r in rows], float)
    mae = np.array([r["mae"] for r in rows], float)
    front = pareto_front(lat, mae)
    fig, ax = plt.subplots(figsize=(8, 5.5), constrained_layout=True)
    sizes = 20 + 12 * np.log10(np.maximum([r["n_params"] or 1 for r in rows], 1))
    onnx = np.array([r["runtime"] == "onnxruntime" for r in rows])
    ax.scatter(lat[onnx], mae[onnx], s=sizes[onnx], label="onnxruntime (1 thread, batch 1)", alpha=0.8)
    ax.scatter(lat[~onnx], mae[~onnx], s=sizes[~onnx], marker="s", label="python/sklearn predict (no ONNX)", alpha=0.8)
    order = np.argsort(lat[front])
    ax.plot(lat[front][order], mae[front][order], "k--", lw=1, label="Pareto frontier")
    for r, x, y in zip(rows, lat, mae):
        ax.annotate(r["model"], (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
    for label, value in (reference or {}).items():
        ax.axhline(value, color="0.6", lw=0.8, ls=":")
        ax.text(lat.min(), value, f" {label}", va="bottom", fontsize=7, color="0.4")
    ax.set_xscale("log")
    ax.set_xlabel("per-window inference latency, µs (log)")
    ax.set_ylabel("LOOCV mean MAE (0–100)")
    ax.set_title("speed against accuracy (marker area ∝ log parameters)")
    ax.legend(fontsize=8, loc="lower left")  # fast and accurate at once: that corner stays empty
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
