"""The report's charts (PNG): the frontier, robustness curves per fault family, augmentation, coverage."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from models.offline.faults.catalog import FAULTS  # noqa: E402
from texture_library.attributes import ATTRIBUTES  # noqa: E402

#: a frontier chart of at most this many scored configurations names every one of them
FEW_POINTS = 8


def frontier_chart(
    rows: list[dict],
    path: Path,
    *,
    title: str,
    target_ms: float | None = None,
    target_label: str | None = None,
    margin_of_best: float | None = None,
) -> Path:
    """MAE against per-frame cost (log), 1 thread filled and 2 threads hollow, the 1-thread Pareto set joined;
    configurations without accuracy (ResNet-50, random weights) as ticks along the top."""
    fig, ax = plt.subplots(figsize=(9, 6), constrained_layout=True)
    scored = [r for r in rows if r["mae"] is not None]
    for threads, style in ((1, {}), (2, {"facecolors": "none"})):
        for glcm, marker in ((True, "o"), (False, "s")):
            pts = [r for r in scored if r["threads"] == threads and r["glcm"] == glcm]
            if pts:
                ax.scatter(
                    [r["frame_ms"] for r in pts],
                    [r["mae"] for r in pts],
                    marker=marker,
                    s=36,
                    alpha=0.85,
                    edgecolors="C0" if threads == 1 else "C1",
                    label=f"{threads} thread{'s' if threads > 1 else ''}, {'+ GLCM' if glcm else 'no GLCM'}",
                    **({"color": "C0"} if threads == 1 else style),
                )
    front = sorted([r for r in scored if r["pareto"] and r["threads"] == 1], key=lambda r: r["frame_ms"])
    # one backbone: its name goes without saying; few points: each is named, not only the Pareto set's
    one_backbone = len({r["backbone"] for r in scored}) == 1
    named = [r for r in scored if r["threads"] == 1] if len(scored) <= FEW_POINTS else front
    for r in named:
        ax.annotate(
            r["label"].replace("effnet-lite0 ", "") if one_backbone else r["label"],
            (r["frame_ms"], r["mae"]),
            textcoords="offset points",
            xytext=(4, 4),
            fontsize=7,
        )
    if front:
        ax.plot([r["frame_ms"] for r in front], [r["mae"] for r in front], "k--", lw=1, label="Pareto set (1 thread)")
        for r in front:
            lo, hi = r["mae_ci"]["lo"], r["mae_ci"]["hi"]
            ax.plot([r["frame_ms"]] * 2, [lo, hi], color="0.6", lw=0.8)
    if scored and margin_of_best is not None:
        best = min(r["mae"] for r in scored if r["threads"] == 1)
        ax.axhline(best + margin_of_best, color="C3", lw=0.8, ls=":", label=f"best + {margin_of_best}")
    if target_ms is not None:
        ax.axvline(target_ms, color="C2", lw=0.8, ls=":", label=target_label or f"{target_ms:g} ms per frame")
    timing_only = [r for r in rows if r["mae"] is None and r["threads"] == 1 and r["glcm"]]
    if timing_only and scored:
        top = max(r["mae"] for r in scored) + 0.3
        ax.scatter(
            [r["frame_ms"] for r in timing_only],
            [top] * len(timing_only),
            marker="|",
            s=200,
            color="C4",
            label="ResNet-50 (random weights: cost only)",
        )
    ax.set_xscale("log")
    ax.set_xlabel("visual embedding per camera frame, ms (log; under load)")
    ax.set_ylabel("LOOCV mean MAE (0–100)")
    ax.set_title(title)
    ax.legend(fontsize=7, loc="upper right")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _axis_value(fault: str, strength: float | None) -> float:
    return 50.0 if strength is None else float(strength)  # clean noise (SNR ∞, stored as None) drawn at 50 dB


def robustness_chart(
    rows: list[dict], family: str, reference: float, path: Path, subset_reference: float | None = None
) -> Path:
    """One panel per fault of a family: MAE against strength for every model; predict-the-mean dashed."""
    faults = [f for f in FAULTS.values() if f.family == family and any(r["fault"] == f.name for r in rows)]
    cols = 4
    nrows = max(1, math.ceil(len(faults) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(4 * cols, 3.2 * nrows), constrained_layout=True, squeeze=False)
    models = sorted({r["model"] for r in rows if r["model"] != "mean"})
    for ax, f in zip(axes.ravel(), faults):
        for k, m in enumerate(models):
            pts = [r for r in rows if r["model"] == m and r["fault"] == f.name]
            if f.name == "no_frame":
                ax.bar(k, pts[-1]["mae"], color=f"C{k}", label=m)
                continue
            ax.plot(
                [_axis_value(f.name, p["strength"]) for p in pts],
                [p["mae"] for p in pts],
                "o-",
                ms=3,
                color=f"C{k}",
                label=m,
            )
        ax.axhline(reference, color="k", ls="--", lw=0.8)
        if subset_reference is not None:
            ax.axhline(subset_reference, color="0.5", ls=":", lw=0.8)
        ax.set_title(f.label, fontsize=9)
        ax.set_xlabel(f.unit if f.name != "noise" else "SNR dB (50 = clean)", fontsize=8)
        if f.name == "noise":
            ax.invert_xaxis()
        if f.name == "no_frame":
            ax.set_xticks([])
        ax.set_ylabel("MAE (0–100)", fontsize=8)
    for ax in axes.ravel()[len(faults) :]:
        ax.axis("off")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower right", fontsize=8)
    fig.suptitle(
        f"{family} faults at test time (held-out texture only); dashed: predict-the-mean = breaking level"
        + ("" if subset_reference is None else "; dotted: the same on the held-out subset (models run on it)")
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def augmentation_chart(blocks: list[dict], reference: float, path: Path) -> Path:
    fig, axes = plt.subplots(
        1, max(1, len(blocks)), figsize=(4.5 * max(1, len(blocks)), 3.5), constrained_layout=True, squeeze=False
    )
    for ax, b in zip(axes.ravel(), blocks):
        f = FAULTS[b["fault"]]
        for key, style in (("before", "o-"), ("after", "s--")):
            ax.plot(
                [_axis_value(f.name, p["strength"]) for p in b[key]],
                [p["mae"] for p in b[key]],
                style,
                ms=3,
                label=f"{key} (trained {'clean' if key == 'before' else 'with augmentation'})",
            )
        ax.axhline(reference, color="k", ls="--", lw=0.8)
        if f.name == "noise":
            ax.invert_xaxis()
        ax.set_title(f"{b['model']}: {f.label}", fontsize=9)
        ax.set_xlabel(f.unit if f.name != "noise" else "SNR dB (50 = clean)", fontsize=8)
        ax.set_ylabel("MAE (0–100)", fontsize=8)
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def coverage_chart(rows: list[dict], model: str, scale: str, path: Path) -> Path:
    """Left: clean coverage per attribute for each target at 80/90 %. Right: coverage as emitted under each
    fault (90 %, per window), with the share of flagged windows."""
    fig, (a1, a2) = plt.subplots(
        1, 2, figsize=(14, 4.5), constrained_layout=True, gridspec_kw={"width_ratios": [1, 2.4]}
    )
    targets = ("window", "ema", "texture")
    width = 0.12
    for t_i, target in enumerate(targets):
        for l_i, level in enumerate((0.8, 0.9)):
            r = next(
                (
                    r
                    for r in rows
                    if r["model"] == model
                    and r["scale"] == scale
                    and r["target"] == target
                    and r["nominal"] == level
                    and r["condition"] == "clean"
                ),
                None,
            )
            if r is None:
                continue
            x = np.arange(len(ATTRIBUTES)) + (t_i * 2 + l_i - 2.5) * width
            a1.bar(
                x,
                [r["per_attribute"][a] for a in ATTRIBUTES],
                width,
                label=f"{target} {int(level * 100)} %",
                color=f"C{t_i}",
                alpha=0.5 + 0.4 * l_i,
            )
    for level in (0.8, 0.9):
        a1.axhspan(level - 0.05, level + 0.05, color="0.85", zorder=0)
    a1.set_xticks(range(len(ATTRIBUTES)), [a.replace("_", "–") for a in ATTRIBUTES], fontsize=8)
    a1.set_ylim(0.5, 1.0)
    a1.set_ylabel("empirical coverage (LOOCV)")
    a1.set_title(f"{model}: clean (grey: nominal ± 5 points)", fontsize=9)
    a1.legend(fontsize=7, ncol=2)
    faulted = [
        r
        for r in rows
        if r["model"] == model
        and r["scale"] == scale
        and r["target"] == "window"
        and r["nominal"] == 0.9
        and r["condition"] != "clean"
    ]
    faulted.sort(key=lambda r: r["condition"])
    x = np.arange(len(faulted))
    a2.bar(x, [r["empirical"] for r in faulted], color=["C2" if r["meets_target"] else "C3" for r in faulted])
    a2.plot(
        x,
        [r["unflagged_empirical"] if r["unflagged_empirical"] is not None else np.nan for r in faulted],
        "k_",
        ms=10,
        label="unflagged windows only",
    )
    a2.plot(x, [r["flagged"] for r in faulted], "v", color="C1", ms=4, label="share flagged")
    a2.axhspan(0.8, 1.0, color="0.9", zorder=0)
    a2.axhline(0.9, color="k", lw=0.8)
    a2.set_xticks(x, [r["condition"] for r in faulted], rotation=90, fontsize=6)
    a2.set_ylim(0, 1.02)
    a2.set_title(f"90 % per-window intervals under each fault (green: meets target; scale {scale})", fontsize=9)
    a2.legend(fontsize=7, loc="lower left")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def windows_chart(rows: list[dict], path: Path) -> Path:
    """Coverage and width of intervals on the mean of n windows, per model, at 80 and 90 %."""
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    for k, model in enumerate(sorted({r["model"] for r in rows})):
        for level, style in ((0.8, "o--"), (0.9, "s-")):
            pts = sorted([r for r in rows if r["model"] == model and r["nominal"] == level], key=lambda r: r["windows"])
            x = [r["seconds"] for r in pts]
            a1.plot(x, [r["empirical"] for r in pts], style, color=f"C{k}", ms=3, label=f"{model} {int(level * 100)} %")
            a2.plot(x, [r["width"] for r in pts], style, color=f"C{k}", ms=3)
    for level in (0.8, 0.9):
        a1.axhspan(level - 0.05, level + 0.05, color="0.9", zorder=0)
    a1.set_xscale("log")
    a2.set_xscale("log")
    a1.set_xlabel("seconds of stroking averaged (n × 0.5 s windows)")
    a2.set_xlabel("seconds of stroking averaged (n × 0.5 s windows)")
    a1.set_ylabel("clean coverage")
    a2.set_ylabel("mean interval width (0–100)")
    a1.legend(fontsize=7)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
