#!/usr/bin/env bash
# Reproduce chisel/depth/checkpoints/change_aware.pt (issue 20): render the training
# phantoms (seeds 1000-1011, never the evaluation seeds 0-99), then train.
#   scripts/train_change_aware.sh [WORK_DIR] [OUT.pt]
set -euo pipefail
WORK=${1:-$(mktemp -d)}
OUT=${2:-chisel/depth/checkpoints/change_aware.pt}
PY=${PYTHON:-.venv/bin/python}
SIM_OPTS=(--bites 3 --phantom-args "--procedure uncinectomy" --frames 16 --preop-frames 12 --spp 4 --quiet)
"$PY" -m sim dataset --seeds 1000-1005 --out "$WORK/train" "${SIM_OPTS[@]}"
"$PY" -m sim dataset --seeds 1006-1011 --out "$WORK/train2" "${SIM_OPTS[@]}"
"$PY" -m chisel depth train --kind change-aware --data "$WORK/train" "$WORK/train2" --out "$OUT" \
    --steps 1000 --batch-size 8 --lr 3e-3 --seed 0 --threads 1 --max-minutes 22
