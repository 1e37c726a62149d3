#!/usr/bin/env bash
# Regenerates reports/tradeoffs/ (the frontier, robustness, intervals, the report).
# Run from the repository root after `make test` created .venv (HAPTICLINK=… overrides the command).
# Long on 2 shared cores (hours): faulted inputs, detector tables and every (model, seed) run are
# cached under artifacts/tradeoffs/ (git-ignored), so a rerun only redoes what is missing; delete
# that folder for a cold run. Timings are taken under whatever load the machine has: rerun the
# frontier alone on a quiet machine for absolute milliseconds (its ratios hold either way).
set -euo pipefail
cd "$(dirname "$0")/../.."
hl() { ${HAPTICLINK:-.venv/bin/hapticlink} "$@"; }
H=${DATASET:-data/hatt-texnet}

# The frontier: every visual configuration timed interleaved, LOOCV MAE with the reference model (ridge-both);
# the rule picks on inner 5-fold CV over every rated texture and is run inside every outer fold for its MAE
hl tradeoffs frontier --dataset $H --model ridge-both
# The same with the served model itself on the three cheapest grids, with and without the spectrum + grid descriptors:
# the table alone (--nested-folds 0: no pick; `selected` inside 79 × 8 × 5 inner fits is hours on 2 cores)
hl tradeoffs frontier --dataset $H --model selected --grids 3 2 1 --resizes native --backbones efficientnet_lite0 \
  --glcm off --descriptor-sets none spectrum,grids --nested-folds 0 --workers 2 --threads 1 2 --repeats 7 \
  --out reports/tradeoffs/frontier-selected.json
# The served configuration: the rule on `selected` itself over the 2×2 grid, no GLCM, on the fp32 and the int8
# backbone, picked on inner 5-fold CV over every rated texture (as `selected` picks its model) and run inside every
# outer fold for its MAE (34 min on 2 busy cores, load 4–8; `--glcm both` doubles the candidates and the time)
hl tradeoffs frontier --dataset $H --model selected --grids 2 --resizes native \
  --backbones efficientnet_lite0 efficientnet_lite0_int8 --glcm off --nested-folds 5 --workers 2 --threads 1 \
  --repeats 7 --out reports/tradeoffs/frontier-quant.json
# Robustness and intervals: faulted inputs of every texture, then fits per (model, seed): curves, breaking points,
# spread, material-group shift, augmentation, interval coverage
hl tradeoffs faults --dataset $H
# The grid the committed page ran (cut to fit 2 shared cores; the CLI default is the full grid):
# every fold for the fast models, the LOOCV folds of 20 held-out textures (fixed, seeded) for the slow
# ones; interval calibration for ridge-both and knn-both; augmentation for ridge-both.
RUNS=${RUNS:-"mean:0 ridge-both:0:cal+aug knn-both:0:cal svr-both:0:sub ann:0,1:sub selected:0:sub"}
hl tradeoffs robustness --dataset $H --workers 2 --subset 20 --runs $RUNS
# The report: the page, its charts and results.json (merges reports/tradeoffs/adaptive.json when present)
hl tradeoffs report --reports reports/tradeoffs
