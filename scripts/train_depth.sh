#!/usr/bin/env bash
# Reproduce chisel/depth/checkpoints/default.pt, the monocular network the workflow fine-tunes
# per patient: the network of 2026-11-22 (default_base.pt; its sidecar holds its own command)
# trained on for 8 epochs on M5, today's uncinectomy with all five steps.
#   scripts/train_depth.sh [WORK_DIR] [OUT.pt]
# Why: default_base.pt saw the small-bite phantoms of 2026-11-22 (one bite, no square cuts).
# On the benchmark's own intraoperative frames (specimen-sized openings seen from close up) its
# median-scaled abs-rel was 0.115; after M5 0.065 (docs/depth.md, "The shipped checkpoint").
# M5: 32 phantoms (seeds 1200-1231; never the evaluation seeds 0-99), a 16-frame preoperative
# sweep and 5 x 16 intraoperative frames each, rendered as the workflow renders (320x256,
# 16 spp): ~9 min on 2 cores. Training: 2 592 frames of 27 phantoms, validation on the other
# 5 (the split is by phantom seed), ~6 min on 2 cores; seeded and deterministic on the CPU.
set -euo pipefail
WORK=${1:-$(mktemp -d)}
OUT=${2:-chisel/depth/checkpoints/default.pt}
BASE=${BASE:-chisel/depth/checkpoints/default_base.pt}
PY=${PYTHON:-.venv/bin/python}
if [ ! -f "$WORK/m5/dataset.json" ]; then
    "$PY" -m sim dataset --seeds 1200-1231 --out "$WORK/m5" --bites 5 \
        --phantom-args "--procedure uncinectomy" --frames 16 --preop-frames 16 --quiet
fi
"$PY" -m chisel depth train --data "$WORK/m5" --init "$BASE" --out "$OUT" \
    --epochs 8 --batch-size 8 --lr 5e-4 --seed 0 --val-fraction 0.15 --frame-step 1 \
    --threads 2 --max-minutes 30 --note "M5: python -m sim dataset --seeds 1200-1231 --out m5 \
--bites 5 --phantom-args '--procedure uncinectomy' --frames 16 --preop-frames 16 (sim at $(git rev-parse --short HEAD))"
