"""reports/fidelity: README.md with Pareto charts, and the `selection` part of results.json.

results.json is shared with other studies (`bandwidth`, `renderer`): this writer replaces only its own
keys and keeps the rest.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on servers and CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from models.offline.evaluation.bootstrap import bootstrap_mean  # noqa: E402
from models.offline.fidelity.study import (  # noqa: E402
    RATING_TARGET,
    SPECTRAL_TARGET_DB,
    WEIGHTS,
    World,
    meets_targets,
    self_rank,
)

OWN_KEYS = ("selection", "default_rule", "selection_synthetic", "selection_study")
LABELS = {
    "rating_distance": "rating distance (0–100)",
    "spectral_distance_db": "spectral distance (dB)",
    "pooled_spectral_distance_db": "pooled spectral (dB)",
    "weighted_spectral_distance_db": "weighted spectral (dB)",
    "mu_difference": "|Δμ|",
}


def pareto_chart(rows: list[dict], title: str, path: Path, default_rule: str) -> Path:
    """Rating distance against spectral distance, one point per rule, 95 % intervals both ways."""
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    for r in rows:
        x, y = r["spectral_distance_db"], r["rating_distance"]
        (xl, xh), (yl, yh) = r["ci95"]["spectral_distance_db"], r["ci95"]["rating_distance"]
        star = r["rule"] == default_rule
        ax.errorbar(
            x,
            y,
            xerr=[[x - xl], [xh - x]],
            yerr=[[y - yl], [yh - y]],
            capsize=3,
            ls="none",
            marker="*" if star else "o",
            ms=14 if star else 7,
            color="C3" if star else None,
        )
        below = r["rule"] in ("physical-lsd", "physical-no-noise-floor")  # neighbours of physical / random
        ax.annotate(r["rule"], (x, y), textcoords="offset points", xytext=(6, -14 if below else 6), fontsize=9)
    ax.axvline(SPECTRAL_TARGET_DB, color="grey", ls="--", lw=1)
    ax.axhline(RATING_TARGET, color="grey", ls="--", lw=1)
    ax.fill_between([0, SPECTRAL_TARGET_DB], 0, RATING_TARGET, color="green", alpha=0.08, label="both targets met")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("spectral distance of the pick's vibration model, dB (lower: feels more alike)")
    ax.set_ylabel("rating distance of the pick, 0–100 (lower: rated more alike)")
    ax.set_title(title)
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def weight_chart(grid: list[dict], path: Path) -> Path:
    """The hybrid's inner-CV trade-off over its weight grid (all rated textures: the served weight)."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    x = [g["spectral_distance_db"] for g in grid]
    y = [g["rating_distance"] for g in grid]
    ax.plot(x, y, "-o")
    for g in grid:
        ax.annotate(
            f"w={g['weight']:g}",
            (g["spectral_distance_db"], g["rating_distance"]),
            fontsize=8,
            textcoords="offset points",
            xytext=(4, 4),
        )
    ax.axvline(SPECTRAL_TARGET_DB, color="grey", ls="--", lw=1)
    ax.axhline(RATING_TARGET, color="grey", ls="--", lw=1)
    ax.set_xlabel("spectral distance, dB")
    ax.set_ylabel("rating distance, 0–100")
    ax.set_title("hybrid: weight per dB of vibration mismatch (leave-one-out, all rated textures)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def paired(per_texture: dict, a: str, b: str, metric: str) -> dict[str, float]:
    """Mean per-texture difference a − b with its texture-level bootstrap interval."""
    return bootstrap_mean(per_texture[a][metric] - per_texture[b][metric])


def _table(rows: list[dict]) -> list[str]:
    head = "| rule | " + " | ".join(LABELS[k] for k in LABELS) + " |"
    out = [head, "|---|" + "---:|" * len(LABELS)]
    for r in rows:
        cells = [f"{r[k]:.2f} [{r['ci95'][k][0]:.2f}, {r['ci95'][k][1]:.2f}]" for k in LABELS]
        out.append(f"| `{r['rule']}` | " + " | ".join(cells) + " |")
    return out


def write_report(
    out: Path,
    command: str,
    default_rule: str,
    hatt: tuple[World, dict, list[dict], dict],
    synthetic: tuple[World, dict, list[dict], dict] | None,
    made_from: dict | None = None,
) -> Path:
    """README.md, pareto_*.png, hybrid_weight.png and results.json's own keys under `out`; made_from: the
    `models.offline.provenance.provenance` record of the inputs read, kept under selection_study."""
    out.mkdir(parents=True, exist_ok=True)
    world, per_texture, rows, info = hatt
    pareto_chart(
        rows,
        f"{world.name}: {len(world.textures)} textures, leave-one-texture-out",
        out / "pareto_hatt.png",
        default_rule,
    )
    weight_chart(info["served_grid"], out / "hybrid_weight.png")
    default = next(r for r in rows if r["rule"] == default_rule)
    met = meets_targets(default)
    study: dict = {
        "targets": {"spectral_distance_db": SPECTRAL_TARGET_DB, "rating_distance": RATING_TARGET},
        "default_rule_meets_targets": met,
        "hybrid": {
            "weight_grid": list(WEIGHTS),
            "fold_weights": {
                f"{w:g}": int(np.sum(np.array(info["fold_weights"]) == w)) for w in sorted(set(info["fold_weights"]))
            },
            "served_weight": info["served_weight"],
            "served_grid": info["served_grid"],
        },
        "windows_per_texture": int(world.whittle.shape[1]),
        "self_rank": {"with_floor": self_rank(world.whittle), "bare": self_rank(world.whittle_bare)},
        "paired_vs_perceptual": {
            rule: {m: paired(per_texture, rule, "perceptual", m) for m in ("rating_distance", "spectral_distance_db")}
            for rule in ("hybrid", "physical")
        },
        "dataset": world.name,
        "command": command,
        **({} if made_from is None else {"provenance": made_from}),
    }
    doc = {"selection": rows, "default_rule": default_rule, "selection_study": study}
    syn_lines: list[str] = []
    if synthetic is not None:
        sworld, sper, srows, sinfo = synthetic
        pareto_chart(
            srows,
            f"synthetic world ({sworld.name}): {len(sworld.textures)} textures, surface bumps",
            out / "pareto_synthetic.png",
            default_rule,
        )
        doc["selection_synthetic"] = srows
        study["synthetic"] = {
            "dataset": sworld.name,
            "served_weight": sinfo["served_weight"],
            "fold_weights": {
                f"{w:g}": int(np.sum(np.array(sinfo["fold_weights"]) == w)) for w in sorted(set(sinfo["fold_weights"]))
            },
            "windows_per_texture": int(sworld.whittle.shape[1]),
        }
        syn_lines = _synthetic_section(sworld, srows, sinfo)
    results = out / "results.json"
    merged = json.loads(results.read_text()) if results.is_file() else {}
    merged.update(doc)
    results.write_text(json.dumps(merged, indent=1) + "\n")
    (out / "README.md").write_text(
        _readme(command, default_rule, world, per_texture, rows, info, met, syn_lines, study)
    )
    return out


def _readme(command, default_rule, world, per_texture, rows, info, met, syn_lines, study) -> str:
    by = {r["rule"]: r for r in rows}
    d, p = by[default_rule], by["perceptual"]
    diff = study["paired_vs_perceptual"]["hybrid"]
    folds = ", ".join(f"w = {k} in {v} folds" for k, v in study["hybrid"]["fold_weights"].items())
    lines = [
        "# Fidelity: what the operator feels",
        "",
        "The service ends at a library entry whose vibration model the operator's device renders. This report",
        "measures how close that entry is to the stroked texture under each selection rule, leave-one-texture-out:",
        "for each stroked texture the library holds every other texture. The rules, and how the hybrid's weight",
        "is tuned inside the folds, were written down before any outer fold was scored: docs/models.md, section",
        '"Fidelity". Reproduce (about a minute on 2 CPU cores, after the datasets are built):',
        "",
        "```",
        command,
        "```",
        "",
        "Columns: `rating_distance` = mean |true ratings of the pick − true ratings of the stroked texture| over",
        "the four attributes (0–100); spectral distance = `texture_library.spectrum.spectral_distance_db` between",
        "the two textures' vibration models (RMS dB over 20–498 Hz, 240 bins 2 Hz apart, the 500 Hz Nyquist bin",
        "left out; mean over 9 operating points); pooled = `pooled_spectral_distance_db`, one RMS over every",
        "operating point and frequency together (the variant an earlier issue quoted; see below); weighted =",
        "the same with each frequency weighted by vibrotactile sensitivity (the inverse of a Pacinian U-shaped",
        "detection threshold, lowest near 250 Hz; Bolanowski et al. 1988; `texture_library/vibrotactile.py`);",
        "|Δμ| = friction coefficient difference. Brackets: texture-level bootstrap 95 % intervals (2000 resamples,",
        f"seed 0). Per-window rules pick once per 500 ms window ({study['windows_per_texture']} windows spread over",
        "each texture's recording, no hysteresis) and a texture's figure is the mean over its windows.",
        "",
        f"## HaTT–TexNet ({len(world.textures)} rated textures)",
        "",
        *_table(rows),
        "",
        "![Pareto: rating distance against spectral distance](pareto_hatt.png)",
        "",
        f"**Default rule: `{default_rule}`** (weight {info['served_weight']:g} per dB for the service, tuned on all",
        f"rated textures; inside the outer folds: {folds}). Targets: spectral ≤ {SPECTRAL_TARGET_DB} dB and rating",
        f"≤ {RATING_TARGET}, both at once. Point estimates: {d['spectral_distance_db']:.2f} dB and",
        f"{d['rating_distance']:.2f} — **{'met' if met else 'not met'}**"
        + (
            f", but only just: the intervals ({d['ci95']['spectral_distance_db'][0]:.2f}–"
            f"{d['ci95']['spectral_distance_db'][1]:.2f} dB, {d['ci95']['rating_distance'][0]:.2f}–"
            f"{d['ci95']['rating_distance'][1]:.2f}) straddle both targets."
            if met
            else "."
        ),
        f"Against today's `perceptual` rule ({p['spectral_distance_db']:.2f} dB, {p['rating_distance']:.2f}) on the",
        f"same textures: spectral distance {diff['spectral_distance_db']['mean']:+.2f} dB",
        f"[{diff['spectral_distance_db']['lo']:+.2f}, {diff['spectral_distance_db']['hi']:+.2f}], rating distance",
        f"{diff['rating_distance']['mean']:+.2f}",
        f"[{diff['rating_distance']['lo']:+.2f}, {diff['rating_distance']['hi']:+.2f}]",
        "(paired bootstrap over textures).",
        "",
        "![The hybrid's trade-off over its weight grid](hybrid_weight.png)",
        "",
        "**What this setup favours.** HaTT–TexNet's tactile streams are rendered from the very ARMA models that",
        "the `physical` rule reads (plus a weaker tangential copy, gravity, a rotated sensor and white sensor",
        "noise, whose level the spectral table assumes known). The physical term is therefore tested on data its",
        "own model class generated, at the stroke's own speed and force: on real recordings, whose spectra no",
        "ARMA fit holds exactly, it will do worse. Its figures here are a best case; the synthetic world below is",
        "the check where that tie is broken.",
        "",
        "**The spectral scale.** The distance is defined once, in `texture_library/spectrum.py`, without the",
        "500 Hz bin: nearly every HaTT MA polynomial has a zero at Nyquist (on a 5 Hz grid the 500 Hz bin sat a",
        "median 47 dB below the 495 Hz bin, more than 30 dB for 77 of the 79 rated models, and 75 models reached the",
        "10⁻¹² log floor there), so that single bin weighed like a wide stretch of the band. The issue that",
        "asked for this study quoted today's rule at 11.06 dB and the spectral oracle at 4.02 dB, on a variant",
        "that pools one RMS over all 9 operating points and a 97-bin grid (20, 25, …, 500 Hz,",
        "Nyquist included). An earlier version of this page said that variant could not be reproduced. It is the",
        "pooled column above (`pooled_spectral_distance_db`), here on this report's grid without Nyquist. On the",
        "issue's grid, with the predictions this page first read (`reports/hatt-texnet/selected/results.json` of",
        "commit ef1dd41, whose rating column gave the issue's 5.15), it gives 10.65 dB and 3.79 dB: near the",
        "quoted figures, not equal to them (`pooled_spectral_distance_db(a, b, np.linspace(20, 500, 97))` per",
        "stroked texture and its pick, averaged). Today's rule on this page:",
        f"{p['pooled_spectral_distance_db']:.2f} dB pooled, {p['spectral_distance_db']:.2f} dB as defined. The",
        f"{SPECTRAL_TARGET_DB} dB target is applied to the defined distance (the mean over operating points).",
        "",
        "**A change after the rules were written.** The first run of `physical`, exactly as pre-registered, compared",
        "each window's spectrum with the bare model spectra: the row `physical-no-noise-floor`"
        f" ({by['physical-no-noise-floor']['spectral_distance_db']:.2f} dB,"
        f" {by['physical-no-noise-floor']['rating_distance']:.2f}), hardly better than random, because the robot's",
        "accelerometer noise (flat, 1.5·10⁻⁵ (m/s²)²/Hz) dominates the top of the band wherever a model is quiet:",
        f"a window ranked its own texture's model at {study['self_rank']['bare']:g} of {len(world.textures)}",
        "(median rank; with",
        f"the floor {study['self_rank']['with_floor']:g}). The table now adds the sensor's noise floor to every model",
        "spectrum (what a measured window holds); the hybrid's weight grid, objective and nesting are unchanged,",
        "and `physical` and `hybrid` above are the corrected rule. This change was made after seeing the first run.",
        "",
        *syn_lines,
    ]
    return "\n".join(lines) + "\n"


def _synthetic_section(world: World, rows: list[dict], info: dict) -> list[str]:
    by = {r["rule"]: r for r in rows}
    return [
        f"## The synthetic world ({len(world.textures)} textures, surface bumps no ARMA spectrum holds)",
        "",
        "Perceptual estimates: the committed leave-one-texture-out predictions of `ridge-both` with the friction,",
        "spatial and taps feature groups (`reports/synthetic/ridge-both+friction+spatial+taps`). Spectral distances",
        "compare the textures' ARMA models, which leave the bumps out; the windows the physical term reads hold",
        "them.",
        "",
        *_table(rows),
        "",
        "![Pareto: synthetic world](pareto_synthetic.png)",
        "",
        f"Here the physical term no longer explains the measured vibration: `physical` picks entries"
        f" {by['physical']['spectral_distance_db']:.2f} dB away (the spectral oracle reaches"
        f" {by['oracle-spectral']['spectral_distance_db']:.2f} dB), and the hybrid (weight {info['served_weight']:g}"
        f" tuned on this world) gains little over `perceptual` ({by['hybrid']['spectral_distance_db']:.2f} against"
        f" {by['perceptual']['spectral_distance_db']:.2f} dB). A library whose models hold the bumps (the rendering"
        " model's `surface`) is what the physical term would need to read.",
        "",
    ]
