"""The feature-group section of a report: what each tactile feature group adds, per attribute.

Reads `<reports>/feature-groups/<model>/<groups>/results.json` (written by `hapticlink evaluate
--extra-groups …`) and `<reports>/feature-groups/mean/results.json` (predict-the-mean), takes
each texture's mean rating from the dataset itself (results.json carry no ratings), and reports
per model and group set, with the intervals of models.offline.evaluation.bootstrap:

- MAE per attribute of the seed-averaged predictions (0–100) with a texture-level bootstrap 95 % interval;
- its ratio to predict-the-mean, with the paired bootstrap interval (the target is ≤ 0.4);
- its change against the same model on MFCC alone, with the paired bootstrap interval (an
  interval that excludes 0 is a contribution, or a loss, beyond resampling noise).

One figure, feature_groups.png: MAE per attribute and group set, one bar per model, with intervals.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.evaluation.bootstrap import (
    N_BOOT,
    bootstrap_errors,
    paired_difference,
    paired_ratio,
    texture_errors,
)
from models.tactile.config import EXTRA_GROUPS
from texture_library.attributes import ATTRIBUTES

KEYS = (*ATTRIBUTES, "mean")  # the columns of every results table of the report
SHORT = {
    "rough_smooth": "rough–smooth",
    "flat_bumpy": "flat–bumpy",
    "sticky_slippery": "sticky–slippery",
    "hard_soft": "hard–soft",
    "mean": "mean",
}
FOLDER = "feature-groups"
TARGET_RATIO = 0.4


def group_label(groups: tuple[str, ...] | list[str]) -> str:
    """ "MFCC" or "MFCC + friction + spatial"."""
    return " + ".join(["MFCC", *groups])


def _order(groups: tuple[str, ...]) -> tuple:
    return (len(groups), [EXTRA_GROUPS.index(g) for g in groups])


def load_group_runs(folder: Path) -> tuple[dict | None, dict[str, dict[tuple[str, ...], dict]]]:
    """(predict-the-mean results or None, {model: {groups: results}}) under folder/feature-groups."""
    root = folder / FOLDER
    mean, runs = None, {}
    for path in sorted(root.rglob("results.json")):
        res = json.loads(path.read_text())
        if res["model"] == "mean":
            mean = res
            continue
        groups = tuple(res.get("features", {}).get("extra_groups", []))
        runs.setdefault(res["model"], {})[groups] = res
    return mean, runs


def _errors(res: dict, textures: list[str], truth: np.ndarray) -> np.ndarray:
    """(T, 4) absolute errors (0–100) of a run's seed-averaged predictions of `textures`."""
    missing = [t for t in textures if t not in res["predictions"]]
    if missing:
        raise ValueError(
            f"{res['model']} results lack predictions of {len(missing)} rated texture(s), e.g. {missing[:3]}"
        )
    return texture_errors(np.array([[res["predictions"][t][a] for a in ATTRIBUTES] for t in textures]), truth)[0]


def _arrays(table: dict) -> tuple[np.ndarray, np.ndarray]:
    """A bootstrap table {"value", "lo", "hi"} → (values over KEYS, (2, len(KEYS)) interval)."""
    return (
        np.array([table["value"][k] for k in KEYS]),
        np.array([[table["lo"][k] for k in KEYS], [table["hi"][k] for k in KEYS]]),
    )


def group_rows(dataset: str | Path, folder: str | Path) -> list[dict]:
    """One row per (model, group set): MAE, its interval, ratio to predict-the-mean and change vs MFCC
    alone, each with its paired bootstrap interval (arrays over KEYS)."""
    mean_res, runs = load_group_runs(Path(folder))
    if not runs:
        return []
    means = Dataset(dataset).mean_ratings()
    first = next(iter(next(iter(runs.values())).values()))
    textures = sorted(first["predictions"])
    if any(t not in means for t in textures):
        raise ValueError(f"{dataset} has no mean rating for some textures of the results in {folder}")
    truth = np.array([means[t] for t in textures])
    ref = None if mean_res is None else _errors(mean_res, textures, truth)
    rows = []
    for model in sorted(runs):
        base = runs[model].get(())
        base_err = None if base is None else _errors(base, textures, truth)
        for groups in sorted(runs[model], key=_order):
            res = runs[model][groups]
            err = _errors(res, textures, truth)
            point, ci = _arrays(bootstrap_errors(err)["mae"])
            row = {"model": model, "groups": groups, "mae": point, "ci": ci, "seeds": res["seeds"]}
            if ref is not None:
                row["ratio"], row["ratio_ci"] = _arrays(paired_ratio(err, ref))
            if base_err is not None and groups:
                row["delta"], row["delta_ci"] = _arrays(paired_difference(err, base_err))
            rows.append(row)
    return rows


def _fmt_ci(v: float, ci: np.ndarray, digits: int = 2) -> str:
    return f"{v:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def feature_group_section(dataset: str | Path, folder: str | Path) -> list[str]:
    """Markdown lines of the section (empty when folder has no feature-group runs); draws the figure."""
    folder = Path(folder)
    rows = group_rows(dataset, folder)
    if not rows:
        return []
    figure = feature_group_figure(rows, folder / "feature_groups.png")
    seeds = sorted({len(r["seeds"]) for r in rows})
    lines = [
        "## Feature groups: what each physical cue adds",
        "",
        "Leave-one-texture-out, the same textures and folds for every row; tactile features are the MFCC set "
        "(40×13 + speed/force statistics) plus the named groups — friction: tangential/normal force ratio; "
        "spatial: acceleration and normal force against position (bump spectrum); taps: tap-transient "
        f"hardness features. {'/'.join(map(str, seeds))} seed(s) per row; MAE of the seed-averaged predictions "
        f"(0–100) with a texture-level bootstrap 95 % interval ({N_BOOT} resamples). *× mean*: ratio to "
        "predict-the-mean (paired interval; target ≤ 0.4). *Δ vs MFCC*: change against the same model on "
        "MFCC alone (paired interval; negative = the group helps).",
        "",
        f"![feature groups]({figure.name})",
        "",
    ]
    for model in dict.fromkeys(r["model"] for r in rows):
        lines += [
            f"### {model}",
            "",
            "| features | " + " | ".join(SHORT[k] for k in KEYS) + " |",
            "|---|" + "---:|" * len(KEYS),
        ]
        for r in (r for r in rows if r["model"] == model):
            cells = []
            for j, _ in enumerate(KEYS):
                cell = _fmt_ci(r["mae"][j], r["ci"][:, j])
                if "ratio" in r:
                    cell += f"<br>{r['ratio'][j]:.2f}× mean [{r['ratio_ci'][0, j]:.2f}, {r['ratio_ci'][1, j]:.2f}]"
                if "delta" in r:
                    cell += f"<br>Δ {_fmt_ci(r['delta'][j], r['delta_ci'][:, j])}"
                cells.append(cell)
            lines.append(f"| {group_label(r['groups'])} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += _target_lines(rows)
    return lines


def _target_lines(rows: list[dict]) -> list[str]:
    rated = [r for r in rows if "ratio" in r]
    if not rated:
        return []
    lines = ["Against the target (each attribute ≤ 0.4 × predict-the-mean), the best row per attribute:", ""]
    for j, k in enumerate(ATTRIBUTES):
        best = min(rated, key=lambda r: r["ratio"][j])
        ok = best["ratio"][j] <= TARGET_RATIO
        lines.append(
            f"- {SHORT[k]}: {best['model']} on {group_label(best['groups'])}: {best['ratio'][j]:.2f} × mean "
            f"[{best['ratio_ci'][0, j]:.2f}, {best['ratio_ci'][1, j]:.2f}] — {'met' if ok else 'not met'}"
        )
    every = [r for r in rated if np.all(r["ratio"][: len(ATTRIBUTES)] <= TARGET_RATIO)]
    lines.append(
        "- one model and group set meeting it on every attribute: "
        + (
            "; ".join(
                f"{r['model']} on {group_label(r['groups'])} ("
                + ", ".join(f"{SHORT[k]} {r['ratio'][j]:.2f}" for j, k in enumerate(ATTRIBUTES))
                + ")"
                for r in every
            )
            if every
            else "none"
        )
    )
    return lines + [""]


def feature_group_figure(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = list(dict.fromkeys(r["model"] for r in rows))
    groups = sorted({r["groups"] for r in rows}, key=_order)
    fig, axes = plt.subplots(
        1, len(ATTRIBUTES), figsize=(4.2 * len(ATTRIBUTES), 4.2), sharey=True, constrained_layout=True
    )
    width = 0.8 / len(models)
    for j, (ax, attr) in enumerate(zip(axes, ATTRIBUTES)):
        for m, model in enumerate(models):
            xs, ys, lo, hi = [], [], [], []
            for g, grp in enumerate(groups):
                r = next((r for r in rows if r["model"] == model and r["groups"] == grp), None)
                if r is None:
                    continue
                xs.append(g + (m - (len(models) - 1) / 2) * width)
                ys.append(r["mae"][j])
                lo.append(r["mae"][j] - r["ci"][0, j])
                hi.append(r["ci"][1, j] - r["mae"][j])
            ax.bar(xs, ys, width, yerr=[lo, hi], capsize=2, label=model)
        ratio_rows = [r for r in rows if "ratio" in r]
        if ratio_rows:
            mean_mae = ratio_rows[0]["mae"][j] / ratio_rows[0]["ratio"][j]
            ax.axhline(mean_mae, color="0.4", ls="--", lw=1, label="predict-the-mean")
            ax.axhline(TARGET_RATIO * mean_mae, color="tab:red", ls=":", lw=1, label="target 0.4 × mean")
        ax.set_xticks(range(len(groups)))
        ax.set_xticklabels(
            ["MFCC" if not g else "+" + "+".join(x[:4] for x in g) for g in groups], rotation=30, ha="right"
        )
        ax.set_title(SHORT[attr])
        ax.set_ylabel("LOOCV MAE (0–100)" if j == 0 else "")
    axes[0].legend(fontsize=7)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
