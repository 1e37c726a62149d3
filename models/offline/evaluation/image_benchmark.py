"""An image-only benchmark (hassan2023): its report table, its withheld predictions and transfer between benchmarks.

    python -m models.offline.evaluation.image_benchmark report   --dataset D --results reports/hassan2023
    python -m models.offline.evaluation.image_benchmark withheld --dataset D --model selected-image --out F.csv
    python -m models.offline.evaluation.image_benchmark transfer --a D1 --b D2 --out reports/hassan2023/transfer.json

Every number is on the 0–100 scale (bipolar error ÷ 2) with its texture-level bootstrap 95 % interval
(`bootstrap.py`); ratios are paired against predict-the-mean's leave-one-out predictions on the same textures.
The published reference predictions are read from the path the dataset header names, never copied.
Per-texture ratings are never written: results hold errors and intervals only.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.evaluation.bootstrap import bootstrap_errors, paired_ratio, texture_errors
from models.offline.evaluation.data import TextureData, load_texture_data
from models.offline.provenance import dataset_inputs, file_input, provenance
from models.visual.config import VisualConfig
from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN

SHORT = ("rs", "fb", "ss", "hs")
# the visual configuration of the hassan2023 report: the frontier's 2×2 backbone grid, every descriptor on
BENCHMARK_VISUAL = VisualConfig(grid=2, descriptors=("lbp", "spectrum", "colour", "grids", "scattering"))


def read_reference(ds: Dataset, textures: list[str]) -> np.ndarray:
    """(T, 4) bipolar reference predictions for `textures`, read from the file the header names (published
    −50…+50 scale × 2); ValueError when the dataset names none or a texture is missing from it."""
    from models.offline.datasets.hassan2023 import read_bipolar_table

    ref = ds.reference_predictions
    if ref is None:
        raise ValueError(f"dataset {ds.name!r} names no reference predictions")
    table = read_bipolar_table(Path(ref["path"]))
    missing = [t for t in textures if t not in table]
    if missing:
        raise ValueError(f"{ref['path']}: no prediction for {len(missing)} texture(s), e.g. {missing[:3]}")
    return np.array([table[t] for t in textures], float)


def score(pred: np.ndarray, truth: np.ndarray, mean_pred: np.ndarray) -> dict:
    """MAE with its interval and the ratio to predict-the-mean with its paired interval; pred (T, 4) or
    (S, T, 4) (seeds: per-texture errors averaged over them)."""
    abs_p, sq_p = texture_errors(pred, truth)
    abs_m, _ = texture_errors(mean_pred, truth)
    return {"mae": bootstrap_errors(abs_p, sq_p)["mae"], "ratio_to_mean": paired_ratio(abs_p, abs_m)}


def _row(name: str, s: dict, note: str = "") -> str:
    m, r = s["mae"], s["ratio_to_mean"]
    ratios = " / ".join(f"{r['value'][a]:.2f}" for a in ATTRIBUTES)
    every = all(r["value"][a] < 1 for a in ATTRIBUTES)
    return (
        f"| {name} | {m['value']['mean']:.2f} [{m['lo']['mean']:.2f}, {m['hi']['mean']:.2f}] | "
        f"{r['value']['mean']:.2f} [{r['lo']['mean']:.2f}, {r['hi']['mean']:.2f}] | {ratios} | "
        f"{'yes' if every else 'no'} | {note} |"
    )


def report(dataset: str | Path, results: str | Path) -> dict:
    """Score every results.json under `results` (hapticlink evaluate outputs) and the reference line on the
    dataset's rated textures; writes results/summary.json and returns it."""
    ds = Dataset(dataset)
    results = Path(results)
    means = ds.mean_ratings()
    runs = {}
    for path in sorted(results.glob("*/results.json")):
        res = json.loads(path.read_text())
        runs[path.parent.name] = res
    if "mean" not in runs:
        raise ValueError(f"{results}: no mean/results.json (predict-the-mean is every ratio's reference)")
    textures = list(runs["mean"]["predictions"])
    truth = np.array([means[t] for t in textures], float)

    def preds(res: dict) -> np.ndarray:
        """(S, T, 4): every seed's leave-one-out predictions."""
        return np.array([[per[t] for t in textures] for per in res["predictions_per_seed"].values()], float)

    mean_pred = preds(runs["mean"])
    summary: dict = {"dataset": ds.name, "n_textures": len(textures), "scale": "0-100", "rows": {}}
    for name, res in runs.items():
        if sorted(res["predictions"]) != sorted(textures):
            raise ValueError(f"{name}: predicts other textures than mean/results.json")
        summary["rows"][name] = {
            **score(preds(res), truth, mean_pred),
            "seeds": res["seeds"],
            "visual_part": res.get("features", {}).get("visual_part"),
            "command": res.get("command"),
        }
    if ds.reference_predictions is not None:
        ref = read_reference(ds, textures)
        summary["reference"] = {"name": ds.reference_predictions["name"], **score(ref, truth, mean_pred)}
    inputs = [*dataset_inputs(dataset), *(file_input("results", results / n / "results.json") for n in runs)]
    summary["provenance"] = provenance(
        inputs, f"python -m models.offline.evaluation.image_benchmark report --dataset {dataset} --results {results}"
    )
    (results / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def table(summary: dict) -> str:
    """The markdown table of a summary: one row per model, the reference line last."""
    lines = [
        "| model | MAE [95 % CI] | ÷ predict-the-mean [95 % CI] | per attribute (rs / fb / ss / hs) "
        "| every attribute < 1 | |",
        "|---|---|---|---|---|---|",
    ]
    rows = sorted(summary["rows"].items(), key=lambda kv: kv[1]["mae"]["value"]["mean"])
    for name, s in rows:
        lines.append(_row(name, s, f"visual: {s['visual_part']}" if s.get("visual_part") else ""))
    if "reference" in summary:
        lines.append(_row(f"published ({summary['reference']['name']})", summary["reference"], "reference line"))
    return "\n".join(lines)


# ---- withheld predictions -----------------------------------------------------------------------
def withheld_predictions(
    dataset: str | Path, model: str, out: str | Path, *, seed: int = 0, visual_config: VisualConfig | None = None
) -> Path:
    """Fit `model` on every rated texture and write the withheld textures' predictions:
    texture + the four bipolar attributes (−100…100), two decimals — the HaTT–TexNet file's format."""
    from models.offline.evaluation.estimator_registry import EstimatorSpec, for_dataset

    ds = Dataset(dataset)
    cfg = visual_config or BENCHMARK_VISUAL
    spec = for_dataset(EstimatorSpec(model), not ds.has_recordings, f"dataset {ds.name!r}")
    train = load_texture_data(dataset, visual_config=cfg)
    test = load_texture_data(dataset, visual_config=cfg, rated="withheld")
    est = spec.build().fit(train, seed)
    pred = np.clip(est.predict(test), RATING_MIN, RATING_MAX)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["texture", *ATTRIBUTES])
        for t, p in zip(test.textures, pred):
            w.writerow([t, *(f"{v:.2f}" for v in p)])
    info = out.with_suffix(".json")
    made = provenance(
        dataset_inputs(dataset),
        f"python -m models.offline.evaluation.image_benchmark withheld --dataset {dataset} --model {model} "
        f"--seed {seed} --out {out}",
    )
    doc = {"model": model, "seed": seed, "fit_info": est.fit_info(), "provenance": made}
    info.write_text(json.dumps(doc, indent=1, default=str))
    return out


# ---- transfer between benchmarks ----------------------------------------------------------------
def image_data(root: str | Path, cfg: VisualConfig, n_views: int = 1) -> TextureData:
    """A dataset's rated textures as image-only data (no tactile features computed, whatever it holds), with
    `n_views` image views each (1: the photo itself; view 0 of every stored set)."""
    from models.offline.featurize import visual_table
    from models.visual.embedding import part_columns, visual_layout

    ds = Dataset(root)
    rated = ds.texture_ids("yes")
    vt = visual_table(root, cfg, n_views=n_views)
    index = {t: i for i, t in enumerate(vt.textures)}
    cols, blocks = part_columns(visual_layout(vt.backbone_dim, cfg), "both")
    means = ds.mean_ratings()
    return TextureData(
        rated,
        ["unknown"] * len(rated),
        [np.zeros((0, 0), np.float32)] * len(rated),
        vt.X[[index[t] for t in rated]][:, :, cols],
        np.array([means[t] for t in rated], np.float32),
        {"dataset": ds.name, "image_only": True, "visual_blocks": blocks},
    )


def loo_recalibrate(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per attribute, each texture's prediction passed through y = a + b·pred fitted by least squares on every
    other texture of the target benchmark (leave-one-out: the texture's own rating never reaches its map)."""
    out = np.empty_like(pred, dtype=float)
    n = len(pred)
    for i in range(n):
        keep = np.arange(n) != i
        for j in range(pred.shape[1]):
            b, a = np.polyfit(pred[keep, j], truth[keep, j], 1)
            out[i, j] = a + b * pred[i, j]
    return np.clip(out, RATING_MIN, RATING_MAX)


def loo_mean(truth: np.ndarray) -> np.ndarray:
    """Predict-the-mean, leave-one-out, on one benchmark."""
    n = len(truth)
    return (truth.sum(axis=0)[None, :] - truth) / (n - 1)


TRANSFER_MODELS = {
    "krr-backbone": ("backbone",),
    "krr-classic": ("glcm", "lbp", "spectrum", "colour", "grids", "scattering"),
    "krr-all": ("backbone", "glcm", "lbp", "spectrum", "colour", "grids", "scattering"),
}


def transfer(a: str | Path, b: str | Path, out: str | Path, *, cfg: VisualConfig | None = None, seed: int = 0) -> dict:
    """Train on every rated texture of one benchmark, score on the other's, both ways: as is, and with a
    per-benchmark linear recalibration fitted leave-one-out on the target benchmark (inside the folds).
    Model: kernel ridge (RBF) on each block set in TRANSFER_MODELS (α, γ per attribute by closed-form LOO on
    the source benchmark), reading each texture's photo itself (one view: augmented views of 100 HaTT photos
    were more CPU than this run had)."""
    from models.offline.evaluation.kernel import KernelRidgeEstimator

    cfg = cfg or BENCHMARK_VISUAL
    data = {"a": image_data(a, cfg), "b": image_data(b, cfg)}
    res: dict = {"scale": "0-100", "directions": {}}
    for src, dst in (("a", "b"), ("b", "a")):
        s, d = data[src], data[dst]
        truth = np.asarray(d.targets, float)
        mean_pred = loo_mean(truth)
        direction = f"{s.meta['dataset']} → {d.meta['dataset']}"
        rows = {"predict-the-mean (target, LOO)": score(mean_pred, truth, mean_pred)}
        for name, blocks in TRANSFER_MODELS.items():
            est = KernelRidgeEstimator("visual", "rbf", views=1, visual_blocks=blocks).fit(s, seed)
            pred = np.clip(est.predict(d.with_targets(None)), RATING_MIN, RATING_MAX)
            rows[f"{name} as is"] = score(pred, truth, mean_pred)
            rows[f"{name} recalibrated"] = score(loo_recalibrate(pred, truth), truth, mean_pred)
            rows[f"{name} as is"]["correlation"] = {
                a_: float(np.corrcoef(pred[:, j], truth[:, j])[0, 1]) for j, a_ in enumerate(ATTRIBUTES)
            }
        res["directions"][direction] = {"n_train": len(s), "n_test": len(d), "rows": rows}
    out = Path(out)
    res["provenance"] = provenance(
        [*dataset_inputs(a, "dataset a"), *dataset_inputs(b, "dataset b")],
        f"python -m models.offline.evaluation.image_benchmark transfer --a {a} --b {b} --out {out}",
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    return res


def transfer_table(res: dict) -> str:
    lines = []
    for direction, block in res["directions"].items():
        lines += [
            f"**{direction}** (train {block['n_train']} textures, score {block['n_test']})",
            "",
            "| model | MAE [95 % CI] | ÷ predict-the-mean [95 % CI] | per attribute (rs / fb / ss / hs) "
            "| every attribute < 1 | r (as is, rs / fb / ss / hs) |",
            "|---|---|---|---|---|---|",
        ]
        for name, s in block["rows"].items():
            corr = s.get("correlation")
            note = " / ".join(f"{corr[a]:+.2f}" for a in ATTRIBUTES) if corr else ""
            lines.append(_row(name, s, note))
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m models.offline.evaluation.image_benchmark")
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("report")
    r.add_argument("--dataset", required=True)
    r.add_argument("--results", required=True)
    w = sub.add_parser("withheld")
    w.add_argument("--dataset", required=True)
    w.add_argument("--model", default="selected-image")
    w.add_argument("--out", required=True)
    w.add_argument("--seed", type=int, default=0)
    t = sub.add_parser("transfer")
    t.add_argument("--a", required=True)
    t.add_argument("--b", required=True)
    t.add_argument("--out", required=True)
    args = p.parse_args(argv)
    if args.cmd == "report":
        print(table(report(args.dataset, args.results)))
    elif args.cmd == "withheld":
        print(f"wrote {withheld_predictions(args.dataset, args.model, args.out, seed=args.seed)}")
    else:
        print(transfer_table(transfer(args.a, args.b, args.out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
