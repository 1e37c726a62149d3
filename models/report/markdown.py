"""`hapticlink report`: one markdown page of every evaluation of a dataset, with its figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.datasets.format import Dataset
from models.evaluation.metrics import split_half_ceiling
from models.report.feature_groups import feature_group_section
from models.report.speed_accuracy import pareto_front, speed_accuracy_chart
from texture_library.attributes import ATTRIBUTES

KEYS = (*ATTRIBUTES, "mean")
SHORT = {"rough_smooth": "rough–smooth", "flat_bumpy": "flat–bumpy", "sticky_slippery": "sticky–slippery", "hard_soft": "hard–soft", "mean": "mean"}
TARGET_MEAN_MAE = 4.5
TARGET_RATIO = 0.4


def load_results(folder: Path) -> list[dict]:
    """Every results.json below folder, with "dir" (relative) added."""
    out = []
    for path in sorted(folder.rglob("results.json")):
        res = json.loads(path.read_text())
        res["dir"] = str(path.parent.relative_to(folder))
        out.append(res)
    return out


def _cell(res: dict, metric: str, key: str) -> str:
    sd = res.get(f"{metric}_std", {}).get(key, 0.0)
    return f"{res[metric][key]:.2f}" + (f" ± {sd:.2f}" if len(res.get("seeds", [])) > 1 else "")


def _table(rows: list[dict], metric: str, ceiling: dict | None) -> list[str]:
    lines = ["| model | modality | seeds | " + " | ".join(SHORT[k] for k in KEYS) + " |",
             "|---|---|---|" + "---:|" * len(KEYS)]
    for r in rows:
        lines.append(f"| {r['dir']} | {r['modality']} | {len(r['seeds'])} | " + " | ".join(_cell(r, metric, k) for k in KEYS) + " |")
    if ceiling is not None:
        lines.append("| *human split-half* | — | — | " + " | ".join(f"*{ceiling[metric][k]:.2f}*" for k in KEYS) + " |")
    return lines


def _ablation_label(res: dict) -> str:
    """The feature choice of a run, per modality it reads: e.g. "visual glcm + tactile mfcc"."""
    f = res.get("features", {})
    parts = []
    if res["modality"] in ("visual", "both"):
        parts.append(f"visual {f.get('visual_part', 'both')}")
    if res["modality"] in ("tactile", "both"):
        parts.append(f"tactile {f.get('tactile_features', 'mfcc')}")
    return " + ".join(parts)


def build_report(dataset: str | Path, folder: str | Path, *, regenerate: str = "") -> Path:
    folder = Path(folder)
    results = load_results(folder)
    if not results:
        raise ValueError(f"no results.json under {folder}; run `hapticlink evaluate … --out {folder}/<model>` first")
    main = sorted((r for r in results if "/" not in r["dir"]), key=lambda r: r["mae"]["mean"])
    if not any(not r["model"].startswith(("mean", "shuffled")) for r in main):
        return _feature_group_page(dataset, folder, results, regenerate)
    ablation = sorted((r for r in results if r["dir"].startswith("ablation/")), key=lambda r: (r["model"], _ablation_label(r)))
    _, _, table = Dataset(dataset).rating_table()
    ceiling = split_half_ceiling(table) if table.shape[1] >= 2 else None
    mean_pred = next((r for r in main if r["model"] == "mean"), None)
    name = main[0]["dataset"]
    lines = [f"# {name}: leave-one-texture-out results", "",
             f"{main[0]['n_textures']} rated textures; every number is on the 0–100 scale (bipolar error ÷ 2), "
             "mean ± std over seeds where there are several. A texture's prediction averages its windows and "
             "comes from a model that never saw that texture (its ratings, its features, nor its early stopping).", ""]
    if regenerate:
        lines += ["Regenerate everything on this page with:", "", "```", regenerate, "```", ""]
    lines += ["## MAE", "", *_table(main, "mae", ceiling), "", "## RMSE", "", *_table(main, "rmse", ceiling), ""]
    best = next(r for r in main if not r["model"].startswith(("mean", "shuffled")))
    lines += _targets(best, mean_pred)
    if ablation:
        lines += ["## Feature ablation (MAE)", "", "| model | features | " + " | ".join(SHORT[k] for k in KEYS) + " |",
                  "|---|---|" + "---:|" * len(KEYS)]
        lines += [f"| {r['model']} | {_ablation_label(r)} | " + " | ".join(_cell(r, 'mae', k) for k in KEYS) + " |" for r in ablation]
        lines.append("")
    lines += feature_group_section(dataset, folder)
    lines += _speed_section(main, folder, mean_pred, ceiling)
    lines += [f"## The best model: {best['model']}", "",
              f"![actual vs predicted]({best['dir']}/actual_vs_predicted.png)", "",
              f"![MAE per group]({best['dir']}/group_mae.png)", "",
              f"![perceptual space]({best['dir']}/perceptual_space.png)", ""]
    out = folder / "README.md"
    out.write_text("\n".join(lines))
    return out


def _feature_group_page(dataset: str | Path, folder: Path, results: list[dict], regenerate: str) -> Path:
    """A page of the feature-group study alone (a folder with no main model runs)."""
    section = feature_group_section(dataset, folder)
    if not section:
        raise ValueError(f"{folder} holds no model runs to report (only {sorted({r['model'] for r in results})})")
    lines = [f"# {results[0]['dataset']}: feature groups, leave-one-texture-out", ""]
    if regenerate:
        lines += ["Regenerate everything on this page with:", "", "```", regenerate, "```", ""]
    out = folder / "README.md"
    out.write_text("\n".join(lines + section))
    return out


def _targets(best: dict, mean_pred: dict | None) -> list[str]:
    lines = ["## Against the targets", ""]
    ok_mean = best["mae"]["mean"] <= TARGET_MEAN_MAE
    lines.append(f"- best model **{best['model']}**: mean MAE {best['mae']['mean']:.2f} "
                 f"(target ≤ {TARGET_MEAN_MAE}: {'met' if ok_mean else 'not met'})")
    if mean_pred is not None:
        for k in ATTRIBUTES:
            ratio = best["mae"][k] / mean_pred["mae"][k]
            lines.append(f"- {SHORT[k]}: {best['mae'][k]:.2f} = {ratio:.2f} × predict-the-mean "
                         f"(target ≤ {TARGET_RATIO}: {'met' if ratio <= TARGET_RATIO else 'not met'})")
    return lines + [""]


def _speed_section(main: list[dict], folder: Path, mean_pred: dict | None, ceiling: dict | None) -> list[str]:
    rows = [{"model": r["dir"], "mae": r["mae"]["mean"], "latency_us": r["latency_us"]["p50_us"],
             "n_params": r.get("n_params"), "runtime": r["latency_us"]["runtime"]}
            for r in main if r.get("latency_us") and not r["model"].startswith(("mean", "shuffled"))]
    if not rows:
        return []
    reference = {}
    if mean_pred is not None:
        reference["predict-the-mean"] = mean_pred["mae"]["mean"]
    if ceiling is not None:
        reference["human split-half"] = ceiling["mae"]["mean"]
    speed_accuracy_chart(rows, folder / "speed_accuracy.png", reference=reference)
    front = pareto_front(np.array([r["latency_us"] for r in rows]), np.array([r["mae"] for r in rows]))
    lines = ["## Speed against accuracy", "",
             "Per-window latency: p50 of 200 single-window calls (batch 1, one thread) of the model fit on all "
             "rated textures — onnxruntime for models that export to ONNX, the estimator's own predict otherwise.", "",
             "![speed against accuracy](speed_accuracy.png)", "",
             "| model | mean MAE | latency p50 (µs) | runtime | parameters | Pareto |", "|---|---:|---:|---|---:|:-:|"]
    for r, f in sorted(zip(rows, front), key=lambda x: x[0]["latency_us"]):
        lines.append(f"| {r['model']} | {r['mae']:.2f} | {r['latency_us']:.0f} | {r['runtime']} | {r['n_params'] or '—'} | {'●' if f else ''} |")
    return lines + [""]
