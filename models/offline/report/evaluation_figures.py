"""Figures of one evaluation: actual vs predicted, MAE per material group, the perceptual space.

The human ratings come in as an argument (from the dataset), never from results.json: committed
results carry predictions only."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on servers and CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from texture_library.attributes import ATTRIBUTES, POLES  # noqa: E402


def prediction_array(results: dict, textures: list[str]) -> np.ndarray:
    """(T, 4) bipolar seed-averaged predictions of results.json, in `textures` order."""
    missing = [t for t in textures if t not in results["predictions"]]
    if missing:
        raise ValueError(f"results of {results.get('model')!r} have no prediction for {missing[:5]}")
    return np.array([[results["predictions"][t][a] for a in ATTRIBUTES] for t in textures])


def actual_vs_predicted(results: dict, textures: list[str], truth: np.ndarray, path: Path) -> Path:
    pred = prediction_array(results, textures)
    fig, axes = plt.subplots(2, 2, figsize=(8, 8), constrained_layout=True)
    for ax, j, attr in zip(axes.ravel(), range(4), ATTRIBUTES):
        ax.plot([-100, 100], [-100, 100], color="0.7", lw=1)
        ax.scatter(truth[:, j], pred[:, j], s=14, alpha=0.8)
        lo, hi = POLES[attr]
        ax.set_xlabel(f"human ({lo} −100 … +100 {hi})")
        ax.set_ylabel("predicted")
        ax.set_title(f"{attr}: MAE {results['mae'][attr]:.2f} (0–100)")
        ax.set_xlim(-100, 100)
        ax.set_ylim(-100, 100)
        ax.set_aspect("equal")
    fig.suptitle(f"{results['model']} on {results['dataset']}: leave-one-texture-out")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def group_heatmap(results: dict, path: Path) -> Path:
    groups = sorted(results["group_mae"])
    table = np.array([[results["group_mae"][g][a] for a in ATTRIBUTES] for g in groups])
    fig, ax = plt.subplots(figsize=(6.5, 0.4 * len(groups) + 1.5), constrained_layout=True)
    im = ax.imshow(table, cmap="viridis", aspect="auto")
    ax.set_xticks(range(4), ATTRIBUTES, rotation=20)
    ax.set_yticks(range(len(groups)), [f"{g} (n={results['group_mae'][g]['n']})" for g in groups])
    for i in range(len(groups)):
        for j in range(4):
            ax.text(
                j,
                i,
                f"{table[i, j]:.1f}",
                ha="center",
                va="center",
                color="w" if table[i, j] < table.max() * 0.6 else "k",
                fontsize=8,
            )
    fig.colorbar(im, ax=ax, label="MAE (0–100)")
    ax.set_title(f"{results['model']}: MAE per material group")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def perceptual_space(results: dict, textures: list[str], truth: np.ndarray, path: Path) -> Path:
    """x hard–soft, y flat–bumpy, bubble size rough–smooth, colour sticky–slippery; human | predicted."""
    pred = prediction_array(results, textures)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True, sharex=True, sharey=True)
    for ax, arr, title in ((axes[0], truth, "human ratings"), (axes[1], pred, "predicted")):
        size = 10 + 140 * (np.clip(arr[:, 0], -100, 100) + 100) / 200
        sc = ax.scatter(
            arr[:, 3],
            arr[:, 1],
            s=size,
            c=arr[:, 2],
            cmap="coolwarm",
            vmin=-100,
            vmax=100,
            alpha=0.75,
            edgecolors="k",
            linewidths=0.3,
        )
        ax.set_xlabel("hard −100 … +100 soft")
        ax.set_title(title)
        ax.axhline(0, color="0.85", lw=0.8)
        ax.axvline(0, color="0.85", lw=0.8)
    axes[0].set_ylabel("flat −100 … +100 bumpy")
    fig.colorbar(sc, ax=axes, label="sticky −100 … +100 slippery")
    fig.suptitle("perceptual space (bubble size: rough → smooth)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def results_figures(results: dict, textures: list[str], truth: np.ndarray, out: Path) -> list[Path]:
    """The three figures of one evaluation. truth: (T, 4) bipolar human ratings of `textures`."""
    out = Path(out)
    truth = np.asarray(truth, float)
    if truth.shape != (len(textures), len(ATTRIBUTES)):
        raise ValueError(f"truth must be ({len(textures)}, {len(ATTRIBUTES)}), got {truth.shape}")
    return [
        actual_vs_predicted(results, textures, truth, out / "actual_vs_predicted.png"),
        group_heatmap(results, out / "group_mae.png"),
        perceptual_space(results, textures, truth, out / "perceptual_space.png"),
    ]


def views_curve(curves: dict[str, list[tuple[int, float, float, float]]], path: Path) -> Path:
    """Mean MAE against the number of image views pooled, one line per model with its 95 % band.

    curves: model → [(views, mae, lo, hi), …] sorted by views."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5), constrained_layout=True)
    for model, pts in curves.items():
        k, mae, lo, hi = (np.array(v, float) for v in zip(*pts))
        ax.plot(k, mae, marker="o", label=model)
        ax.fill_between(k, lo, hi, alpha=0.15)
    ax.set_xscale("log", base=2)
    ticks = sorted({p[0] for pts in curves.values() for p in pts})
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.set_xlabel("image views pooled per texture")
    ax.set_ylabel("LOOCV mean MAE (0–100), 95 % band")
    ax.set_title("pooling views: error against views")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
