#!/usr/bin/env bash
# The accuracy benchmarks recorded in BENCHMARKS.md: no TTR vs SfM-TTR online (the node's
# windows) vs offline (the whole sequence, as the paper), default model,
# params/kitti_accurate.yaml (the overlapping windows and 200 steps of BENCHMARKS.md §1-2; the
# faster default params/kitti.yaml is measured by scripts/benchmark_speed.py, §5).
#   bash scripts/run_benchmarks.sh [OUT_DIR]        (~25 min on 2 CPU cores)
# 1. a generated KITTI-format drive of held-out domain B (the model was trained on domain A);
# 2. ../shared/data/hololens_000: 100 real indoor frames, GT depth in mm.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-bench}
SFM_TTR=.venv/bin/sfm-ttr
SHARED=../shared/data
PARAMS=params/kitti_accurate.yaml

$SFM_TTR generate --kitti-raw "$OUT/data/raw" --kitti-gt "$OUT/data/gt" --frames 40 \
    --domain B --seed 1
$SFM_TTR benchmark --kitti-raw "$OUT/data/raw" --kitti-gt "$OUT/data/gt" \
    --drive 2011_09_26_drive_0001_sync --params-file "$PARAMS" --out "$OUT/synthetic_B"

if [ -d "$SHARED/hololens_000" ]; then
    $SFM_TTR benchmark --images "$SHARED/hololens_000/images" \
        --intrinsics "$SHARED/hololens_000/K.txt" --gt-depth "$SHARED/hololens_000/depth" \
        --gt-scale 1000 --params-file "$PARAMS" --out "$OUT/hololens_000"
else
    echo "run_benchmarks: $SHARED/hololens_000 not found, skipping it" >&2
fi
