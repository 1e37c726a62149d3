"""Intervals from study runs: do the intervals cover what they claim, clean, under every fault, under shift?

For held-out texture i the calibration is built from other textures only — the calibration
models of models.offline.tradeoffs.folds, which never saw i (nor the texture they predict) — exactly as
`hapticlink train` calibrates a served model by K-fold CV over its training textures. Three
targets are calibrated and scored: per window, the EMA-smoothed stream (alpha 0.5, the service's
default) and per texture (the mean of its windows). Two scales: none, and feature-space distance
from the fold's OOD detector. Windows flagged out of distribution get the widened interval.

Coverage is averaged over textures (each texture weighs 1, however many windows it has), per
attribute; conditions: clean, every fault variant, leave-one-material-group-out.
"""

from __future__ import annotations

import numpy as np

from models.inference.intervals import IntervalCalibration, ema_flags
from models.offline.calibrate import EMA_ALPHA, Prediction, calibrate, rows_of
from models.offline.evaluation.bootstrap import bootstrap_mean
from models.offline.tradeoffs.detection import Check
from models.offline.tradeoffs.faulted import CLEAN
from models.offline.tradeoffs.folds import calibration_sources
from models.offline.tradeoffs.study import StudyRun
from texture_library.attributes import ATTRIBUTES, REPORT_SCALE

TARGETS = ("window", "ema", "texture")
SERVED_TARGETS = ("window", "ema")  # what the service emits; `recommend` chooses among these
SCALE_KINDS = ("none", "distance")
LEVELS = (0.8, 0.9)
CLEAN_TOLERANCE = 0.05
FAULT_TOLERANCE = 0.10


def flags_of(check: Check, target: str) -> np.ndarray:
    if target == "window":
        return check.flags
    if target == "ema":
        return ema_flags(check.flags, EMA_ALPHA)
    return np.array([check.flags.mean() > 0.5])


def score(cal: IntervalCalibration, pred: Prediction, truth: np.ndarray, check: Check, level: float) -> dict:
    """Per-attribute coverage fraction, flagged fraction, coverage of unflagged rows, mean width (0–100 scale)."""
    p, t, d = rows_of(pred, truth, check.distance, cal.target)
    flags = flags_of(check, cal.target)
    lo, hi = cal.interval(p, np.sqrt(d) if cal.scale == "distance" else None, level, ood=flags)
    inside = (t >= lo - 1e-9) & (t <= hi + 1e-9)
    ok = ~flags
    return {
        "covered": inside.mean(axis=0),
        "flagged": float(flags.mean()),
        "covered_unflagged": inside[ok].mean(axis=0) if ok.any() else None,
        "width": float(np.mean(hi - lo) * REPORT_SCALE),
    }


def _summary(scores: list[dict]) -> dict:
    """Coverage over textures (each weighs 1), flagged share and width: what the rule reads, without an interval."""
    covered = np.mean([s["covered"] for s in scores], axis=0)
    unflagged = [s["covered_unflagged"] for s in scores if s["covered_unflagged"] is not None]
    return {
        "empirical": float(covered.mean()),
        "per_attribute": dict(zip(ATTRIBUTES, map(float, covered))),
        "flagged": float(np.mean([s["flagged"] for s in scores])),
        "unflagged_empirical": float(np.mean(unflagged)) if unflagged else None,
        "width": float(np.mean([s["width"] for s in scores])),
        "n_textures": len(scores),
    }


def _aggregate(scores: list[dict]) -> dict:
    """_summary with empirical_ci: the texture-level bootstrap interval of the mean coverage."""
    ci = bootstrap_mean(np.array([s["covered"] for s in scores]).mean(axis=1))
    return {**_summary(scores), "empirical_ci": [ci["lo"], ci["hi"]]}


def meets_target(summary: dict, condition: str, level: float) -> bool:
    """Clean: every attribute within ±5 points of nominal. A fault: coverage ≥ nominal − 10 points as emitted, and
    on the unflagged windows too (or ≥ 90 % of windows flagged)."""
    if condition == CLEAN:
        return all(abs(v - level) <= CLEAN_TOLERANCE for v in summary["per_attribute"].values())
    unflagged = summary["unflagged_empirical"]
    ok_unflagged = unflagged is None or unflagged >= level - FAULT_TOLERANCE or summary["flagged"] >= 0.9
    return bool(summary["empirical"] >= level - FAULT_TOLERANCE and ok_unflagged)


#: (condition, target, scale, level) → [(texture index, its score)]
Scores = dict[tuple[str, str, str, float], list[tuple[int, dict]]]


def coverage_scores(
    run: StudyRun,
    truth: np.ndarray,
    part: np.ndarray,
    checks: dict[str, list[Check]],
    distances: dict,
    shift_checks: dict[int, Check] | None = None,
    groups: list[str] | None = None,
) -> Scores:
    """Every held-out texture's coverage score for every condition × target × scale × level of one run (with
    calibration tasks)."""
    if not run.calib:
        raise ValueError(f"{run.model} seed {run.seed} has no calibration fits; run it with calibration")
    n = len(truth)
    collected: Scores = {}
    for i in range(n):
        material = [(j, run.calib[key][j], distances[key][j]) for j, key in calibration_sources(part, i)]
        prior = truth[np.arange(n) != i]
        for target in TARGETS:
            for scale_kind in SCALE_KINDS:
                cal = calibrate(
                    material, truth, prior, target, scale_kind, LEVELS, "out-of-fold (models.offline.tradeoffs.folds)"
                )
                for key, preds in run.loocv.items():
                    if preds[i] is None or key not in checks or len(checks[key][i].flags) == 0:
                        continue
                    for level in LEVELS:
                        collected.setdefault((key, target, scale_kind, level), []).append(
                            (i, score(cal, preds[i], truth[i], checks[key][i], level))
                        )
    if run.shift_inner and shift_checks is not None and groups is not None:
        garr = np.asarray(groups)
        for g, oof in run.shift_inner.items():
            # inner out-of-fold material inside the training groups; scale "none" (no inner detectors)
            material = [(j, p, np.ones(len(p.windows))) for j, p in oof.items()]
            prior = truth[garr != g]
            for target in TARGETS:
                cal = calibrate(
                    material, truth, prior, target, "none", LEVELS, "inner 5-fold inside the training groups"
                )
                for i in np.flatnonzero(garr == g):
                    for level in LEVELS:
                        collected.setdefault(("shift", target, "none", level), []).append(
                            (int(i), score(cal, run.shift[int(i)], truth[i], shift_checks[int(i)], level))
                        )
    return collected


def coverage_rows(run: StudyRun, scores: Scores, *, with_ci: bool = True) -> list[dict]:
    """One row per condition × target × scale × level: coverage over the textures scored, and its verdict."""
    summarise = _aggregate if with_ci else _summary
    rows = []
    for (condition, target, scale_kind, level), per_texture in sorted(scores.items(), key=lambda kv: str(kv[0])):
        agg = summarise([sc for _, sc in per_texture])
        rows.append(
            {
                "model": run.model,
                "seed": run.seed,
                "condition": condition,
                "target": target,
                "scale": scale_kind,
                "nominal": level,
                **agg,
                "meets_target": meets_target(agg, condition, level),
            }
        )
    return rows


def nested_recommendation(run: StudyRun, scores: Scores) -> dict:
    """`recommend` run inside the folds: for each held-out texture the rule reads only the other textures'
    coverages, and that texture is scored with the setting it picked. Not strictly blind to it: the other
    textures' coverages come from calibrations that drew on its residuals too (a doubly held-out calibration per
    fold would remove that, at the cost of refitting every one).

    Returns {"picks": {"target/scale": folds}, "clean": [{"nominal", "empirical", "empirical_ci",
    "per_attribute", "n_textures"}]}: clean coverage of the procedure per level, each texture weighing 1.
    ValueError unless every served setting scores the same textures clean (a pick could leave one unscored)."""
    served = {k: v for k, v in scores.items() if k[1] in SERVED_TARGETS}
    scored = {tuple(sorted(i for i, _ in per)) for (condition, *_), per in served.items() if condition == CLEAN}
    if len(scored) != 1 or len(next(iter(scored))) < 2:
        raise ValueError(f"every served setting must score the same ≥ 2 textures clean, got {sorted(scored)}")
    textures = list(next(iter(scored)))
    picks: dict[str, int] = {}
    chosen: dict[float, list[np.ndarray]] = {}
    for i in textures:
        others = {k: [(j, sc) for j, sc in per if j != i] for k, per in served.items()}
        pick = recommend(coverage_rows(run, {k: v for k, v in others.items() if v}, with_ci=False))
        name = f"{pick['target']}/{pick['scale']}"
        picks[name] = picks.get(name, 0) + 1
        for (condition, target, scale_kind, level), per in served.items():
            if condition == CLEAN and (target, scale_kind) == (pick["target"], pick["scale"]):
                chosen.setdefault(level, []).extend(np.asarray(sc["covered"], float) for j, sc in per if j == i)
    clean = []
    for level, covered in sorted(chosen.items()):
        per_texture = np.array(covered)
        ci = bootstrap_mean(per_texture.mean(axis=1))
        clean.append(
            {
                "nominal": level,
                "empirical": float(per_texture.mean()),
                "empirical_ci": [ci["lo"], ci["hi"]],
                "per_attribute": dict(zip(ATTRIBUTES, map(float, per_texture.mean(axis=0)))),
                "n_textures": len(per_texture),
            }
        )
    return {"picks": picks, "clean": clean}


WINDOW_COUNTS = (1, 2, 4, 5, 10, 20)


def coverage_after_n_windows(
    run: StudyRun, truth: np.ndarray, part: np.ndarray, counts: tuple[int, ...] = WINDOW_COUNTS
) -> list[dict]:
    """Clean coverage and width of intervals on the mean of n consecutive windows (non-overlapping blocks of the
    20-window segment), calibrated the same way on the calibration textures' blocks; unnormalised."""
    from models.offline.calibrate import Prediction as P

    def blocks(p: P, n: int) -> P:
        m = len(p.windows) // n
        return P(p.texture, p.windows[: m * n].reshape(m, n, -1).mean(axis=1))

    rows = []
    size = len(truth)
    shortest = min(
        min(len(p.windows) for p in run.loocv[CLEAN]),
        min(len(p.windows) for by_key in run.calib.values() for p in by_key.values()),
    )
    for n in [n for n in counts if n <= shortest]:
        scores = {lv: [] for lv in LEVELS}
        for i in range(size):
            material = [
                (j, blocks(run.calib[key][j], n), np.ones(len(run.calib[key][j].windows) // n))
                for j, key in calibration_sources(part, i)
            ]
            cal = calibrate(material, truth, truth[np.arange(size) != i], "window", "none", LEVELS)
            test = blocks(run.loocv[CLEAN][i], n)
            check = Check(np.zeros(len(test.windows), bool), [[] for _ in test.windows], np.ones(len(test.windows)))
            for lv in LEVELS:
                scores[lv].append(score(cal, test, truth[i], check, lv))
        for lv in LEVELS:
            agg = _aggregate(scores[lv])
            rows.append(
                {
                    "model": run.model,
                    "windows": n,
                    "seconds": n * 0.5,
                    "nominal": lv,
                    "empirical": agg["empirical"],
                    "per_attribute": agg["per_attribute"],
                    "width": agg["width"],
                }
            )
    return rows


def recommend(rows: list[dict]) -> dict:
    """The (target, scale) to serve: clean coverage within ±5 points at every level and attribute; then the
    most fault conditions meeting their target; then the narrowest. Targets per window or EMA (what the
    service emits), not per texture."""
    best = None
    for target in SERVED_TARGETS:
        for scale_kind in SCALE_KINDS:
            mine = [r for r in rows if r["target"] == target and r["scale"] == scale_kind]
            clean = [r for r in mine if r["condition"] == CLEAN]
            if not clean:
                continue
            faults = [r for r in mine if r["condition"] != CLEAN]
            key = (
                all(r["meets_target"] for r in clean),
                sum(r["meets_target"] for r in faults),
                -float(np.mean([r["width"] for r in clean])),
            )
            if best is None or key > best[0]:
                best = (
                    key,
                    {
                        "target": target,
                        "scale": scale_kind,
                        "clean_ok": key[0],
                        "faults_ok": key[1],
                        "faults_total": len(faults),
                        "clean_width": -key[2],
                    },
                )
    return best[1] if best else {}
