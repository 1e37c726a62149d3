"""`hapticlink report`: one markdown page of every evaluation of a dataset, with its figures.

The human ratings are read from the dataset (`--dataset`), never from results.json: committed
results hold predictions only. Every MAE on the page carries a texture-level bootstrap 95 %
interval, and each model is compared, texture by texture, with the reference model (ridge-visual).
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.evaluation.bootstrap import bootstrap_errors, paired_difference, texture_errors
from models.offline.evaluation.families import with_siblings
from models.offline.evaluation.metrics import split_half_ceiling
from models.offline.report.feature_groups import FOLDER as GROUPS_FOLDER
from models.offline.report.feature_groups import KEYS, SHORT, feature_group_section
from models.offline.report.speed_accuracy import pareto_front, speed_accuracy_chart
from texture_library.attributes import ATTRIBUTES

TARGET_MEAN_MAE = 4.5
TARGET_RATIO = 0.4
TARGET_HARD_SOFT = 4.5
REFERENCE = "ridge-visual"  # the paired comparisons' baseline
HEADLINE = "selected"  # chosen inside the folds by the rule in docs/models.md
FAMILIES_FOLDER = "families"  # runs with `--leave-out family`, each beside its main-table twin
OLDER = "†"
# The README's results table: its rows (report folder → what the model is), in this order.
README_ROWS = {
    "selected": "picked per attribute inside each fold among the 4 pooled models below, on the served 2×2 no-GLCM int8 "
    "image features (served; withheld predictions)",
    "selected-exact-loo": "`selected` with its kernel ridges' α, γ and touch weight chosen by exact leave-one-out "
    "(a sensitivity row: the rule keeps the criterion it was fixed with)",
    "mean-pooled": "mean of ridge-, krr- and ksvr-pooled",
    "krr-pooled": "kernel ridge (RBF), 8 views pooled, touch weighed per attribute",
    "ksvr-pooled": "kernel SVR (RBF), 8 views pooled, touch weighed per attribute",
    "ridge-pooled": "ridge (linear kernel), 8 views pooled, touch weighed per attribute",
    "ann-ensemble": "mean of 3 ANN seeds (served before `selected`)",
    "stack-both": "ridge + kNN + SVR, stacked",
    "ann": "ANN baseline (paper), 3 seeds",
    "svr-visual": "SVR, image features",
    "ridge-visual": "ridge, image features (the Δ reference)",
    "ridge-both": "ridge, image + touch",
    "vtnet-compact": "Visuo-tactile Net, compact",
    "svr-tactile-windows": "paper's Tactile SVM",
    "mean": "predict the mean",
}
README_BEGIN = (
    "<!-- results table: written by `hapticlink report --dataset data/hatt-texnet --reports reports/hatt-texnet "
    "--readme README.md`; edits here are overwritten -->"
)
README_END = "<!-- end of results table -->"


def load_results(folder: Path) -> list[dict]:
    """Every results.json below folder, with "dir" (relative) added."""
    out = []
    for path in sorted(folder.rglob("results.json")):
        res = json.loads(path.read_text())
        res["dir"] = str(path.parent.relative_to(folder))
        out.append(res)
    return out


def attach_errors(res: dict, truth: dict[str, np.ndarray]) -> None:
    """Per-texture errors of a run against the dataset's ratings, and their bootstrap intervals, into res.

    Uses the per-seed predictions when the run stored them (the interval is then that of the mean over
    seeds, the table's number); older runs stored only the seed-averaged prediction."""
    textures = sorted(res["predictions"])
    missing = [t for t in textures if t not in truth or not np.all(np.isfinite(truth[t]))]
    if missing:
        raise ValueError(f"{res['dir']}: the dataset has no ratings for {missing[:5]}; pass the dataset the run used")
    y = np.array([truth[t] for t in textures])
    per_seed = res.get("predictions_per_seed")
    if per_seed:
        pred = np.array([[per_seed[s][t] for t in textures] for s in sorted(per_seed, key=int)])
    else:
        pred = np.array([[res["predictions"][t][a] for a in ATTRIBUTES] for t in textures])
    res["_textures"] = textures
    res["_abs"], res["_sq"] = texture_errors(pred, y)
    res["_boot"] = bootstrap_errors(res["_abs"], res["_sq"])
    # an older multi-seed run: its interval is that of the seed-averaged prediction, not of the seed mean
    res["_older"] = "predictions_per_seed" not in res


def _ci(boot: dict, key: str, digits: int = 1) -> str:
    return f"[{boot['lo'][key]:.{digits}f}, {boot['hi'][key]:.{digits}f}]"


def _cell(res: dict, metric: str, key: str) -> str:
    boot = res["_boot"][metric]
    value = res[metric][key]
    sd = res.get(f"{metric}_std", {}).get(key, 0.0)
    seeds = f" ± {sd:.2f}" if len(res.get("seeds", [])) > 1 and key == "mean" else ""
    return f"{value:.2f}{seeds} {_ci(boot, key)}"


def _label(res: dict) -> str:
    return res["dir"] + (f" {OLDER}" if res["_older"] else "")


def _views(res: dict) -> str:
    return "—" if res.get("views") is None and res["modality"] in ("tactile", "none") else str(res.get("views") or 1)


def _table(rows: list[dict], metric: str, ceiling: dict | None, reference: dict | None) -> list[str]:
    ref_col = reference is not None and metric == "mae"
    head = (
        "| model | modality | views | seeds | "
        + " | ".join(SHORT[k] for k in KEYS)
        + (f" | Δ mean vs {reference['dir']} |" if ref_col else " |")
    )
    lines = [head, "|---|---|---:|---:|" + "---:|" * (len(KEYS) + ref_col)]
    for r in rows:
        cells = [_cell(r, metric, k) for k in KEYS]
        if ref_col:
            cells.append("—" if r is reference else _delta(r, reference, "mean"))
        lines.append(f"| {_label(r)} | {r['modality']} | {_views(r)} | {len(r['seeds'])} | " + " | ".join(cells) + " |")
    if ceiling is not None:
        lines.append(
            "| *human split-half* | — | — | — | "
            + " | ".join(f"*{ceiling[metric][k]:.2f}*" for k in KEYS)
            + (" | |" if ref_col else " |")
        )
    return lines


def _paired(res: dict, reference: dict) -> dict:
    key = "_paired"
    if key not in res:
        if res["_textures"] != reference["_textures"]:
            raise ValueError(f"{res['dir']} and {reference['dir']} were scored on different textures")
        res[key] = paired_difference(res["_abs"], reference["_abs"])
    return res[key]


def _delta(res: dict, reference: dict, k: str) -> str:
    d = _paired(res, reference)
    return f"{d['value'][k]:+.2f} {_ci(d, k, 2)}"


def _ablation_label(res: dict) -> str:
    """The feature choice of a run, per modality it reads: e.g. "visual glcm + tactile mfcc"."""
    f = res.get("features", {})
    parts = []
    if res["modality"] in ("visual", "both"):
        parts.append(f"visual {f.get('visual_part', 'both')}")
    if res["modality"] in ("tactile", "both"):
        parts.append(f"tactile {f.get('tactile_features', 'mfcc')}")
    return " + ".join(parts)


def build_report(
    dataset: str | Path,
    folder: str | Path,
    *,
    regenerate: str = "",
    reference: str = REFERENCE,
    readme: str | Path | None = None,
    readme_rows: dict[str, str] = README_ROWS,
) -> Path:
    """Write folder/README.md from every results.json below folder; `reference`: the model every other is
    compared with, texture by texture (a folder name of the main table). With `readme`, also rewrite the
    results table of that file (between README_BEGIN and README_END) with `readme_rows` (folder → what)."""
    folder = Path(folder)
    results = load_results(folder)
    if not results:
        raise ValueError(f"no results.json under {folder}; run `hapticlink evaluate … --out {folder}/<model>` first")
    ds = Dataset(dataset)
    truth = ds.mean_ratings()
    for r in results:
        attach_errors(r, truth)
    main = sorted((r for r in results if "/" not in r["dir"]), key=lambda r: r["mae"]["mean"])
    if all(r["dir"].startswith(GROUPS_FOLDER + "/") for r in results):  # the feature-group study alone
        return _feature_group_page(dataset, folder, results, regenerate)
    ablation = sorted(
        (r for r in results if r["dir"].startswith("ablation/")), key=lambda r: (r["model"], _ablation_label(r))
    )
    views = [r for r in results if r["dir"].startswith("views/")]
    families = [r for r in results if r["dir"].startswith(FAMILIES_FOLDER + "/")]
    _, _, table = ds.rating_table()
    ceiling = split_half_ceiling(table) if table.shape[1] >= 2 else None
    mean_pred = next((r for r in main if r["model"] == "mean"), None)
    reference_run = next((r for r in main if r["dir"] == reference), None)
    headline = next((r for r in main if r["dir"] == HEADLINE), None)
    scored = [r for r in main if not r["model"].startswith(("mean", "shuffled"))]
    best = scored[0] if scored else main[0]
    name = main[0]["dataset"]
    lines = [
        f"# {name}: leave-one-texture-out results",
        "",
        f"{main[0]['n_textures']} rated textures; every number is on the 0–100 scale (bipolar error ÷ 2). "
        "A texture's prediction averages its windows and comes from a model that never saw that texture (its "
        "ratings, its features, nor its early stopping). Each MAE/RMSE carries a texture-level bootstrap 95 % "
        "interval in brackets (textures resampled with replacement, 2000 draws); with several seeds the mean "
        "shows ± the standard deviation of the seeds' MAEs (population: ÷ n seeds), and the interval is that of "
        "the mean over seeds. *views*: image views pooled into a texture's visual input. Human ratings are read "
        "from the dataset, not stored with the "
        f"results. {OLDER}: an earlier run that stored only its seed-averaged prediction — its interval is that "
        "prediction's.",
        "",
    ]
    if regenerate:
        lines += ["Regenerate everything on this page with:", "", "```", regenerate, "```", ""]
    if headline is not None:
        lines += _headline(headline, best)
    lines += [
        "## MAE",
        "",
        *_table(main, "mae", ceiling, reference_run),
        "",
        "## RMSE",
        "",
        *_table(main, "rmse", ceiling, None),
        "",
    ]
    if reference_run is not None:
        lines += _paired_section(main, reference_run)
    lines += _targets(headline, best, mean_pred)
    if headline is not None:
        lines += _selection_section(headline)
    if views:
        lines += _views_section(views, folder, main)
    if families:
        lines += _families_section(families, main)
    if ablation:
        lines += [
            "## Feature ablation (MAE)",
            "",
            "| model | features | " + " | ".join(SHORT[k] for k in KEYS) + " |",
            "|---|---|" + "---:|" * len(KEYS),
        ]
        lines += [
            f"| {r['model']} | {_ablation_label(r)} | " + " | ".join(_cell(r, "mae", k) for k in KEYS) + " |"
            for r in ablation
        ]
        lines.append("")
    lines += feature_group_section(dataset, folder)
    lines += _speed_section(main, folder, mean_pred, ceiling)
    shown = headline or best
    lines += [
        f"## {'The selected model' if headline else 'The best model'}: {shown['dir']}",
        "",
        f"![actual vs predicted]({shown['dir']}/actual_vs_predicted.png)",
        "",
        f"![MAE per group]({shown['dir']}/group_mae.png)",
        "",
        f"![perceptual space]({shown['dir']}/perceptual_space.png)",
        "",
    ]
    out = folder / "README.md"
    out.write_text("\n".join(lines))
    if readme is not None:
        write_readme_table(Path(readme), readme_table(main, readme_rows, reference_run, ceiling, mean_pred))
    return out


def _feature_group_page(dataset: str | Path, folder: Path, results: list[dict], regenerate: str) -> Path:
    """A page of the feature-group study alone (a folder whose only runs are under feature-groups/)."""
    section = feature_group_section(dataset, folder)
    if not section:
        raise ValueError(f"{folder} holds no model runs to report (only {sorted({r['model'] for r in results})})")
    lines = [f"# {results[0]['dataset']}: feature groups, leave-one-texture-out", ""]
    if regenerate:
        lines += ["Regenerate everything on this page with:", "", "```", regenerate, "```", ""]
    out = folder / "README.md"
    out.write_text("\n".join(lines + section))
    return out


def _latency(res: dict) -> str:
    us = (res.get("latency_us") or {}).get("p50_us")
    if us is None:
        return ""
    return f"{us / 1000:.1f} ms" if us >= 1000 else f"{us:.0f} µs"


def readme_table(
    main: list[dict], rows: dict[str, str], reference: dict | None, ceiling: dict | None, mean_pred: dict | None
) -> list[str]:
    """The README's results table: `rows` (report folder → what it is) in that order, each with its MAE per
    attribute, mean MAE with its bootstrap 95 % interval, the paired Δ against `reference` and the latency,
    then the human ceiling and one line on the headline model against the targets.

    main: runs of the main table with errors attached (attach_errors)."""
    by_dir = {r["dir"]: r for r in main}
    missing = [d for d in rows if d not in by_dir]
    if missing:
        raise ValueError(f"the README table needs results for {missing}; run `hapticlink evaluate` for them first")
    ref = reference["dir"] if reference is not None else "—"
    lines = [
        f"| model | what | {' | '.join(SHORT[k] for k in ATTRIBUTES)} | mean MAE [95 %] | Δ vs {ref} [95 %] "
        "| latency / window |",
        "|---|---|" + "---:|" * (len(ATTRIBUTES) + 3),
    ]
    for d, what in rows.items():
        r = by_dir[d]
        sd = f" ± {r['mae_std']['mean']:.2f}" if len(r.get("seeds", [])) > 1 and "mae_std" in r else ""
        mean = f"{r['mae']['mean']:.2f}{sd} {_ci(r['_boot']['mae'], 'mean', 2)}"
        mean = f"**{mean}**" if d == HEADLINE else mean
        delta = "—" if reference is None or r is reference else _delta(r, reference, "mean")
        lines.append(
            f"| {_label(r)} | {what} | "
            + " | ".join(f"{r['mae'][k]:.2f}" for k in ATTRIBUTES)
            + f" | {mean} | {delta} | {_latency(r)} |"
        )
    if ceiling is not None:
        lines.append(
            "| *human split-half* | two halves of the raters | "
            + " | ".join(f"*{ceiling['mae'][k]:.2f}*" for k in KEYS)
            + " | | |"
        )
    head = by_dir.get(HEADLINE)
    if head is not None:
        lines += ["", _target_sentence(head, mean_pred)]
    return lines


def _target_sentence(res: dict, mean_pred: dict | None) -> str:
    """One sentence: the model against the mean-MAE, per-attribute and hard–soft targets, by how much it misses."""
    m = res["mae"]["mean"]
    out = [
        f"`{res['dir']}` against the targets: mean MAE {m:.2f} "
        + (
            f"meets ≤ {TARGET_MEAN_MAE}"
            if m <= TARGET_MEAN_MAE
            else f"misses ≤ {TARGET_MEAN_MAE} by {m - TARGET_MEAN_MAE:.2f}"
        )
    ]
    hs = res["mae"]["hard_soft"]
    out.append(
        f"hard–soft {hs:.2f} "
        + (
            f"meets ≤ {TARGET_HARD_SOFT}"
            if hs <= TARGET_HARD_SOFT
            else f"misses ≤ {TARGET_HARD_SOFT} by {hs - TARGET_HARD_SOFT:.2f}"
        )
    )
    if mean_pred is not None:
        ratios = [
            f"{SHORT[k]} {res['mae'][k] / mean_pred['mae'][k]:.2f}"
            + ("" if res["mae"][k] / mean_pred["mae"][k] <= TARGET_RATIO else " (missed)")
            for k in ATTRIBUTES
        ]
        out.append(f"MAE ÷ predict-the-mean (target ≤ {TARGET_RATIO}): " + ", ".join(ratios))
    return "; ".join(out) + "."


def write_readme_table(readme: Path, lines: list[str]) -> None:
    """Replace what lies between README_BEGIN and README_END in readme with lines."""
    text = readme.read_text()
    if (
        text.count(README_BEGIN) != 1
        or text.count(README_END) != 1
        or text.index(README_BEGIN) > text.index(README_END)
    ):
        raise ValueError(
            f"{readme} needs one line {README_BEGIN!r} and, below it, one line {README_END!r} around its results table"
        )
    head, rest = text.split(README_BEGIN)
    _, tail = rest.split(README_END)
    readme.write_text(head + README_BEGIN + "\n" + "\n".join(lines) + "\n" + README_END + tail)


def _headline(headline: dict, best: dict) -> list[str]:
    lines = [
        "## Headline",
        "",
        f"- **selected inside the folds** (`{headline['dir']}`, the rule in docs/models.md, nested CV): mean MAE "
        f"**{headline['mae']['mean']:.2f}** {_ci(headline['_boot']['mae'], 'mean', 2)} — no selection bias in the "
        "model: every outer fold picked its own model from its training textures."
        + (
            " The image features it reads (the served 2×2 patches, no GLCM, int8 backbone) were picked by the "
            "frontier's fixed rule on inner cross-validation over these textures with this model, as it picks its "
            "own candidates; the rule run inside every outer fold is the number to quote for both choices together "
            "(`reports/tradeoffs/frontier-quant.json`, docs/models.md)."
            if _reads_served_images(headline)
            else ""
        ),
    ]
    if best is not headline:
        lines.append(
            f"- best of the table (`{best['dir']}`, picked after seeing these numbers, so optimistic): "
            f"{best['mae']['mean']:.2f} {_ci(best['_boot']['mae'], 'mean', 2)}"
        )
    return lines + [""]


def _reads_served_images(res: dict) -> bool:
    """Whether a run read the served image configuration (models.offline.featurize.SERVED_VISUAL)."""
    from models.offline.featurize import SERVED_VISUAL

    features = res.get("features") or {}
    config = features.get("visual_config") or {}
    return (
        features.get("backbone") == SERVED_VISUAL.backbone
        and config.get("grid") == SERVED_VISUAL.grid
        and config.get("glcm") == SERVED_VISUAL.glcm
    )


def _paired_section(main: list[dict], reference: dict) -> list[str]:
    lines = [
        f"## Paired comparison against {reference['dir']}",
        "",
        f"MAE(model) − MAE({reference['dir']}) over the same textures, with the interval from resampling textures for "
        "both at once; negative is better, an interval that excludes 0 is a difference these textures support.",
        "",
        "| model | " + " | ".join(SHORT[k] for k in KEYS) + " |",
        "|---|" + "---:|" * len(KEYS),
    ]
    for r in main:
        if r is reference:
            continue
        lines.append(f"| {_label(r)} | " + " | ".join(_delta(r, reference, k) for k in KEYS) + " |")
    return lines + [""]


def _targets(headline: dict | None, best: dict, mean_pred: dict | None) -> list[str]:
    lines = ["## Against the targets", ""]
    for tag, res in (("selected inside the folds", headline), ("best of the table", best)):
        if res is None or (tag == "best of the table" and res is headline):
            continue
        ok = res["mae"]["mean"] <= TARGET_MEAN_MAE
        lines.append(
            f"- {tag} **{res['dir']}**: mean MAE {res['mae']['mean']:.2f} {_ci(res['_boot']['mae'], 'mean', 2)} "
            f"(target ≤ {TARGET_MEAN_MAE}: {'met' if ok else 'not met'})"
        )
        if mean_pred is not None:
            for k in ATTRIBUTES:
                ratio = res["mae"][k] / mean_pred["mae"][k]
                extra = ""
                if k == "hard_soft":
                    extra = (
                        f"; ≤ {TARGET_HARD_SOFT} absolute: {'met' if res['mae'][k] <= TARGET_HARD_SOFT else 'not met'}"
                    )
                lines.append(
                    f"  - {SHORT[k]}: {res['mae'][k]:.2f} = {ratio:.2f} × predict-the-mean "
                    f"(target ≤ {TARGET_RATIO}: {'met' if ratio <= TARGET_RATIO else 'not met'}{extra})"
                )
    return lines + [""]


def _selection_section(res: dict) -> list[str]:
    """What the outer folds picked, per attribute (counts over folds and seeds)."""
    counts = {a: Counter() for a in ATTRIBUTES}
    for run in res.get("fold_info", []):
        for fold in run:
            for a, c in fold.get("chosen", {}).items():
                counts[a][c] += 1
    if not any(counts.values()):
        return []
    candidates = sorted({c for cnt in counts.values() for c in cnt})
    total = sum(counts[ATTRIBUTES[0]].values())
    lines = [
        "## What the folds selected",
        "",
        f"Per attribute, how often each candidate was picked by the inner cross-validation of the {total} outer "
        "folds (all seeds). The served model applies the same rule to all rated textures "
        "(its card says what it picked).",
        "",
        "| candidate | " + " | ".join(SHORT[a] for a in ATTRIBUTES) + " |",
        "|---|" + "---:|" * len(ATTRIBUTES),
    ]
    for c in candidates:
        lines.append(f"| {c} | " + " | ".join(str(counts[a][c]) for a in ATTRIBUTES) + " |")
    return lines + [""]


def _views_section(views: list[dict], folder: Path, main: list[dict] = ()) -> list[str]:
    """Runs under views/: error against views pooled (fit and shown k views), and against the views a
    held-out texture is shown through when the model was fit on more (`--test-views`). Where views/ has no
    run of a model at some k and the main table's run of that model pooled k views, that run (all its
    seeds) stands in: the same computation, not run twice; its cell is marked *."""
    from models.offline.report.evaluation_figures import views_curve

    def key(r: dict) -> str:
        return r["model"] if r.get("test_views") is None else f"{r['model']}, fit on {r['views']}, shown k"

    def x(r: dict) -> int:
        return r["test_views"] if r.get("test_views") is not None else r["views"]

    by_model: dict[str, list[dict]] = {}
    for r in views:
        by_model.setdefault(key(r), []).append(r)
    counts = sorted({x(r) for r in views})
    for r in main:
        rs = by_model.get(r["model"])
        if (
            rs is not None
            and r.get("test_views") is None
            and r.get("views") in counts
            and r["views"] not in {x(v) for v in rs}
        ):
            rs.append(r)
    for rs in by_model.values():
        rs.sort(key=x)
    views_curve(
        {
            m: [(x(r), r["mae"]["mean"], r["_boot"]["mae"]["lo"]["mean"], r["_boot"]["mae"]["hi"]["mean"]) for r in rs]
            for m, rs in by_model.items()
        },
        folder / "views_curve.png",
    )
    lines = [
        "## Views pooled",
        "",
        "Mean MAE against k, the number of image views pooled per texture (view 0 the photo, then its augmented "
        "views). Plain rows: fit and predicted with k views pooled. *fit on 8, shown k*: fit on 8 pooled views, "
        "the held-out texture shown only its first k — a service that pooled k camera frames into a model "
        "trained on 8 (`models.visual.pooling`). *: the main table's run of the model (all its seeds), which "
        "pooled that many views.",
        "",
        "![MAE against views pooled](views_curve.png)",
        "",
        "| model | " + " | ".join(f"k = {k}" for k in counts) + " |",
        "|---|" + "---:|" * len(counts),
    ]
    for m, rs in by_model.items():
        at = {x(r): r for r in rs}
        lines.append(
            f"| {m} | "
            + " | ".join(
                (_cell(at[k], "mae", "mean") + (" *" if "/" not in at[k]["dir"] else "")) if k in at else "—"
                for k in counts
            )
            + " |"
        )
    return lines + [""]


def _families_section(families: list[dict], main: list[dict]) -> list[str]:
    """Runs under families/ (`--leave-out family`) against the main table's run of the same model and features:
    on every texture, and on those with a sibling (the only ones whose fold changes)."""
    lines = [
        "## A new material, not a new sample: families left out",
        "",
        "Some textures are samples of one product line: their names differ only in a trailing number "
        "(carpet_1, carpet_3; floortile_1 … floortile_7; sandpaper_100, sandpaper_220). Leaving one texture out keeps "
        "its siblings in training; `hapticlink evaluate --leave-out family` keeps its whole family out of the fold "
        "that predicts it (`models/offline/evaluation/families.py`; a nested rule's inner folds split the "
        "remaining training textures as usual). Textures without a sibling get the same fold either way. Δ: MAE "
        "(families out) − MAE (texture out), paired over the same textures; positive: worse on a new material.",
        "",
        "| model | textures | leave one texture out | leave its family out | Δ [95 %] |",
        "|---|---|---:|---:|---:|",
    ]
    for run in sorted(families, key=lambda r: r["dir"]):
        twin = next(
            (
                r
                for r in main
                if r["model"] == run["model"]
                and r.get("options") == run.get("options")
                and r.get("features") == run.get("features")
                and r.get("views") == run.get("views")
            ),
            None,
        )
        if twin is None or twin["_textures"] != run["_textures"]:
            lines.append(
                f"| {run['dir']} | — | no main-table run of the same model and features on the same textures | | |"
            )
            continue
        siblings = with_siblings(run["_textures"])
        for label, rows in (("all", slice(None)), (f"with a sibling ({len(siblings)})", siblings)):
            if label != "all" and not siblings:
                continue
            a, b = twin["_abs"][rows], run["_abs"][rows]
            boot_a, boot_b = bootstrap_errors(a)["mae"], bootstrap_errors(b)["mae"]
            d = paired_difference(b, a)
            lines.append(
                f"| {run['dir']} | {label if label != 'all' else f'all ({len(a)})'} | "
                f"{boot_a['value']['mean']:.2f} {_ci(boot_a, 'mean', 2)} | "
                f"{boot_b['value']['mean']:.2f} {_ci(boot_b, 'mean', 2)} | "
                f"{d['value']['mean']:+.2f} {_ci(d, 'mean', 2)} |"
            )
    return lines + [""]


def _hosts_line(runs: list[dict]) -> str:
    """Which hosts the latencies were timed on (absolute times belong to them): each results.json's `hardware`."""
    hosts = sorted(
        {
            f"{h['model']} ({', '.join(h['isa']) if h.get('isa') else 'ISA flags unknown'})"
            for h in (r.get("hardware", {}).get("host") for r in runs)
            if h
        }
    )
    missing = sum(1 for r in runs if not r.get("hardware", {}).get("host"))
    said = f"Timed on {'; '.join(hosts)}." if hosts else ""
    if missing:
        said += (
            f" {missing} of {len(runs)} runs predate the record of their CPU (their `hardware` names the platform "
            "and core count only): absolute times, comparable only between runs of one host."
        )
    return said.strip()


def _speed_section(main: list[dict], folder: Path, mean_pred: dict | None, ceiling: dict | None) -> list[str]:
    timed = [r for r in main if r.get("latency_us") and not r["model"].startswith(("mean", "shuffled"))]
    rows = [
        {
            "model": r["dir"],
            "mae": r["mae"]["mean"],
            "latency_us": r["latency_us"]["p50_us"],
            "n_params": r.get("n_params"),
            "runtime": r["latency_us"]["runtime"],
        }
        for r in timed
    ]
    if not rows:
        return []
    reference = {}
    if mean_pred is not None:
        reference["predict-the-mean"] = mean_pred["mae"]["mean"]
    if ceiling is not None:
        reference["human split-half"] = ceiling["mae"]["mean"]
    speed_accuracy_chart(rows, folder / "speed_accuracy.png", reference=reference)
    front = pareto_front(np.array([r["latency_us"] for r in rows]), np.array([r["mae"] for r in rows]))
    lines = [
        "## Speed against accuracy",
        "",
        "Per-window latency: p50 of 200 single-window calls (batch 1, one thread) of the model fit on all "
        "rated textures — onnxruntime for models that export to ONNX, the estimator's own predict otherwise. "
        + _hosts_line(timed),
        "",
        "![speed against accuracy](speed_accuracy.png)",
        "",
        "| model | mean MAE | latency p50 (µs) | runtime | parameters | Pareto |",
        "|---|---:|---:|---|---:|:-:|",
    ]
    for r, f in sorted(zip(rows, front), key=lambda x: x[0]["latency_us"]):
        lines.append(
            f"| {r['model']} | {r['mae']:.2f} | {r['latency_us']:.0f} | {r['runtime']} | {r['n_params'] or '—'} "
            f"| {'●' if f else ''} |"
        )
    return lines + [""]
