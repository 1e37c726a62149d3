#!/usr/bin/env bash
# Regenerates every number under reports/: datasets, leave-one-texture-out evaluations, report pages,
# the exported model and the withheld-texture predictions. Run from the repository root after
# `make test` (or `make demo`) has created .venv. About 7 hours on 2 CPU cores (the nested-CV
# `selected` runs are the longest part; the benchmarks at the end about an hour); each step is cached or
# skippable by hand. Seeds are fixed; folds run in parallel processes. The report reads the human ratings from $H (never stored in results).
# Steps run in dependency order: each report after every input it reads (evaluations → their pages and the
# served model → fidelity, which reads `selected` and the synthetic ridge-both run → the frontier study, which
# reads the evaluations and the service benchmark's adaptive.json → the benchmarks, whose bandwidth run fills
# keys of reports/fidelity/results.json). Every report records the SHA-256 of what it read; the last step checks
# that none is stale (tests/reports/test_report_inputs.py).
set -euo pipefail
cd "$(dirname "$0")/.."
hl() { .venv/bin/hapticlink "$@"; }
H=data/hatt-texnet
S=data/physics-synthetic-48     # the synthetic world (world_version 2: bumps, friction and taps the sensors can read)
P=data/physics-hatt-texnet      # HaTT–TexNet rebuilt for the feature-group study (friction from each model's mu, HaTT's taps)
# feature-group study: MFCC alone, + each group, + friction and spatial (synthetic only), + every group
GROUPSETS=("" "friction" "spatial" "taps" "friction spatial" "friction spatial taps")
GROUPSETS_HATT=("" "friction" "spatial" "taps" "friction spatial taps")
# seeds per model (ridge is deterministic: any seeds give the same numbers; one ANN seed, and no ANN
# and one SVR seed on HaTT–TexNet: CPU time)
declare -A SEEDS=([ridge-tactile]="0 1 2" [ridge-both]="0 1 2" [svr-both]="0 1 2" [ann]="0")
declare -A SEEDS_HATT=([ridge-tactile]="0" [ridge-both]="0" [svr-both]="0")

# ---- datasets (HaTT–TexNet read from ../shared, never copied into the repo) --------------------
[ -f $H/dataset.json ] || hl dataset build --source hatt-texnet --path ../shared/data/hatt-texnet --out $H
hl dataset check $H
[ -f $S/dataset.json ] || hl dataset build --source synthetic --n-textures 48 --duration 10 --out $S
[ -f $P/dataset.json ] || hl dataset build --source hatt-texnet --path ../shared/data/hatt-texnet --out $P

# ---- HaTT–TexNet: the selected model (nested CV: the rule in docs/models.md) and its candidates ----
# the served visual configuration: the frontier's pick inside the folds (2×2 patches, no GLCM, the int8 backbone;
# reports/tradeoffs/frontier-quant.json, docs/models.md)
SERVED=(--visual-grid 2 --no-glcm --backbone efficientnet_lite0_int8)
hl evaluate --dataset $H --model selected "${SERVED[@]}" --out reports/hatt-texnet/selected --seeds 0 1 2
# the same rule with the kernel ridges' exact leave-one-out criterion: a sensitivity row (docs/models.md)
hl evaluate --dataset $H --model selected-exact-loo "${SERVED[@]}" --out reports/hatt-texnet/selected-exact-loo --seeds 0 1 2
# a new material, not a new sample: each fold keeps the held-out texture's whole family out (docs/models.md)
hl evaluate --dataset $H --model selected "${SERVED[@]}" --leave-out family --out reports/hatt-texnet/families/selected --seeds 0 1 2
for m in ridge-pooled krr-pooled; do  # deterministic: one seed
  hl evaluate --dataset $H --model $m --out reports/hatt-texnet/$m --seeds 0
done
for m in ksvr-pooled mean-pooled; do
  hl evaluate --dataset $H --model $m --out reports/hatt-texnet/$m --seeds 0 1 2
done
# ---- MAE against the number of image views pooled (1, 2, 4, 8) -----------------------------------
for k in 1 2 4 8; do
  for m in ridge-visual krr-pooled selected; do
    [ "$m-v$k" = selected-v8 ] && continue  # the main selected run pooled 8 views; the report uses it there
    flags=(); [ $m = selected ] && flags=("${SERVED[@]}")  # selected as served; the others on the default
    hl evaluate --dataset $H --model $m --views $k "${flags[@]}" --out reports/hatt-texnet/views/$m-v$k --seeds 0 \
      --no-figures
  done
done
# ---- HaTT–TexNet: classical models and controls (3 seeds) ---------------------------------------
for m in mean shuffled-ridge-both ridge-visual ridge-tactile ridge-both knn-visual knn-tactile knn-both \
         svr-visual svr-tactile svr-both svr-tactile-windows stack-both; do
  hl evaluate --dataset $H --model $m --out reports/hatt-texnet/$m --seeds 0 1 2
done
# ---- networks: the paper's baselines and the Visuo-tactile Net variants -------------------------
for m in vision-1dcnn haptic-cnn tactile-cnn-lstm vtnet-visual vtnet-tiny vtnet-tactile vtnet-compact; do
  hl evaluate --dataset $H --model $m --out reports/hatt-texnet/$m --seeds 0
done
hl evaluate --dataset $H --model ann --out reports/hatt-texnet/ann --seeds 0 1 2
hl evaluate --dataset $H --model shuffled-ann --out reports/hatt-texnet/shuffled-ann --seeds 0
# the mean of three ANN seeds (one ONNX graph); seed s trains members 3s, 3s+1, 3s+2
hl evaluate --dataset $H --model ann-ensemble --out reports/hatt-texnet/ann-ensemble --seeds 0 1 2
# ---- feature ablation -----------------------------------------------------------------------------
for part in backbone glcm both; do
  hl evaluate --dataset $H --model svr-visual --visual-part $part --out reports/hatt-texnet/ablation/svr-visual-$part --seeds 0
  hl evaluate --dataset $H --model ann --visual-part $part --out reports/hatt-texnet/ablation/ann-visual-$part --seeds 0
done
for feat in mfcc dwt dft; do
  hl evaluate --dataset $H --model svr-tactile-windows --tactile-features $feat --out reports/hatt-texnet/ablation/svr-tactile-windows-$feat --seeds 0
done
for feat in dwt dft; do  # ann with MFCC is ablation/ann-visual-both
  hl evaluate --dataset $H --model ann --tactile-features $feat --out reports/hatt-texnet/ablation/ann-tactile-$feat --seeds 0
done
hl report --dataset $H --reports reports/hatt-texnet --regenerate "bash reports/regenerate.sh" --readme README.md

# ---- the model for the service and the withheld textures: the selection rule on all rated textures --
hl train --dataset $H --model selected "${SERVED[@]}" --seed 0 --metrics reports/hatt-texnet/selected/results.json --out artifacts/hatt-selected.onnx
hl predict --model artifacts/hatt-selected.onnx --dataset $H --textures withheld --out reports/hatt-texnet/withheld_predictions.csv
# ---- LOOCV on the serial, process and Ray backends (same jobs, wall times in one run) -------------
.venv/bin/python -m benchmarks.loocv --dataset $H --model ridge-pooled

# ---- synthetic world: how much of the known mapping is recovered ---------------------------------
for m in mean ridge-tactile ridge-visual ridge-both svr-tactile svr-visual svr-both knn-both ann; do
  hl evaluate --dataset $S --model $m --out reports/synthetic/$m --seeds 0
done
for feat in dwt dft; do
  hl evaluate --dataset $S --model ridge-tactile --tactile-features $feat --out reports/synthetic/ablation/ridge-tactile-$feat --seeds 0
done
# the physics feature groups: friction + spatial, and every group (the demo's model)
hl evaluate --dataset $S --model ridge-both --extra-groups friction spatial --out reports/synthetic/ridge-both+friction+spatial --seeds 0 1 2
hl evaluate --dataset $S --model ridge-both --extra-groups friction spatial taps --out reports/synthetic/ridge-both+friction+spatial+taps --seeds 0 1 2
# ---- feature groups: each group's contribution per attribute (both datasets) ----------------------
groups_study() {  # dataset, reports folder, name of the group-set array, name of the seeds array (model → seeds)
  local ds=$1 out=$2; local -n sets=$3 seeds=$4
  hl evaluate --dataset $ds --model mean --out $out/feature-groups/mean --seeds 0 --no-figures
  for m in "${!seeds[@]}"; do
    for g in "${sets[@]}"; do
      name=${g// /+}
      # shellcheck disable=SC2086  # $g is a list of group names, ${seeds[$m]} a list of seeds
      hl evaluate --dataset $ds --model $m --extra-groups $g --out $out/feature-groups/$m/${name:-mfcc} \
        --seeds ${seeds[$m]} --no-figures
    done
  done
}
groups_study $S reports/synthetic GROUPSETS SEEDS
groups_study $P reports/physics-hatt-texnet GROUPSETS_HATT SEEDS_HATT
# the committed SVR row on MFCC alone ran 3 seeds (its seed-averaged prediction is what the page compares)
hl evaluate --dataset $P --model svr-both --extra-groups --out reports/physics-hatt-texnet/feature-groups/svr-both/mfcc \
  --seeds 0 1 2 --no-figures
hl report --dataset $S --reports reports/synthetic --regenerate "bash reports/regenerate.sh"
hl report --dataset $P --reports reports/physics-hatt-texnet --regenerate "bash reports/regenerate.sh"

# ---- what the operator feels: selection rules leave-one-texture-out (reports/fidelity) ------------
hl fidelity --dataset $H --predictions reports/hatt-texnet/selected/results.json \
  --synthetic-dataset $S --synthetic-predictions reports/synthetic/ridge-both+friction+spatial+taps/results.json \
  --out reports/fidelity

# ---- speed–accuracy frontier, robustness, calibrated intervals --------------------------------
# adaptive serving first: the tradeoffs page merges reports/tradeoffs/adaptive.json
.venv/bin/python -m benchmarks.adaptive
bash reports/tradeoffs/regenerate.sh

# ---- hassan2023: touch-rated textures, image only (reports/hassan2023) ---------------------------
# The photos and the published predictions are read from ../shared (never copied). Visual features: the
# frontier's 2×2 backbone grid with every texture descriptor on (≈ 20 min for 91 photos × 8 views on 2
# busy cores). One seed (selected-image: three): kernel ridge is deterministic; the nested selections' inner shuffles are the only
# seeded part (CPU time).
HS=data/hassan2023
HV=(--visual-grid 2 --descriptors lbp spectrum colour grids scattering)
HR=reports/hassan2023
[ -f $HS/dataset.json ] || hl dataset build --source hassan2023 --path ../shared/data/hassan2023 --out $HS --no-features
hl dataset check $HS
hl evaluate --dataset $HS --model mean --out $HR/mean --seeds 0 "${HV[@]}" --no-figures
hl evaluate --dataset $HS --model selected-image --out $HR/selected-image --seeds 0 1 2 "${HV[@]}" --no-figures
hl evaluate --dataset $HS --model selected --out $HR/selected --seeds 0 "${HV[@]}" --no-figures
for part in backbone classic both; do
  hl evaluate --dataset $HS --model ridge-visual --visual-part $part --out $HR/ridge-visual-$part --seeds 0 "${HV[@]}" --no-figures
  hl evaluate --dataset $HS --model krr-pooled --visual-part $part --out $HR/krr-pooled-$part --seeds 0 "${HV[@]}" --no-figures
  hl evaluate --dataset $HS --model knn-visual --visual-part $part --out $HR/knn-visual-$part --seeds 0 "${HV[@]}" --no-figures
done
for part in backbone classic; do
  hl evaluate --dataset $HS --model svr-visual --visual-part $part --out $HR/svr-visual-$part --seeds 0 "${HV[@]}" --no-figures
done
py() { .venv/bin/python -m models.offline.evaluation.image_benchmark "$@"; }
py report --dataset $HS --results $HR
py withheld --dataset $HS --model selected-image --seed 0 --out $HR/withheld_predictions.csv
py transfer --a $H --b $HS --out $HR/transfer.json   # HaTT–TexNet ↔ hassan2023, same visual configuration
.venv/bin/python -m benchmarks.descriptors --image ../shared/data/hassan2023/images/t002.jpg --out reports/bench/descriptors.json
# the same image-only models on HaTT–TexNet (looks), for the per-benchmark comparison
hl evaluate --dataset $H --model mean --out $HR/hatt-image/mean --seeds 0 "${HV[@]}" --no-figures
for m in krr-backbone-image krr-all-image krr-classic-image; do
  hl evaluate --dataset $H --model $m --out $HR/hatt-image/$m --seeds 0 "${HV[@]}" --no-figures
  hl evaluate --dataset $HS --model $m --out $HR/$m --seeds 0 "${HV[@]}" --no-figures
done
hl evaluate --dataset $H --model selected-image --out $HR/hatt-image/selected-image --seeds 0 1 2 "${HV[@]}" --no-figures
py report --dataset $H --results $HR/hatt-image
py report --dataset $HS --results $HR

# ---- speed (reports/bench; the bandwidth and renderer keys of reports/fidelity/results.json) ---------------
# after fidelity, whose results.json the bandwidth benchmark fills (each writer keeps the other's keys)
.venv/bin/python -m benchmarks
# ---- nothing above may be stale: every report's recorded inputs still hash the same -------------------
.venv/bin/python -m pytest -q tests/reports/test_report_inputs.py
