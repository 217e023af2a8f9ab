#!/usr/bin/env bash
# The window-check measurements behind docs/decisions.md "Window checks" (the `sfm` loss), params/kitti.yaml:
#   bash scripts/studies/check_benchmarks.sh [OUT_DIR]        (~90 min on 2 quiet CPU cores)
# 1. what each window's refinement did to its own frames against GT, and the checks' verdicts
#    (scripts/studies/check_outcomes.py) on the hard drive, the domain-B drive and hololens_000;
# 2. sfm-ttr benchmark with the checks on (defaults) and off, reset and continue policies.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:-bench/checks}
SFM_TTR=.venv/bin/sfm-ttr
H=../shared/data/hololens_000
DRIVE=2011_09_26_drive_0001_sync
OFF=(--set check.min_parallax=0
     --set check.max_reprojection_error=0 --set check.max_scale_jump=0)

$SFM_TTR generate --scenario hard --kitti-raw "$OUT/hard/raw" --kitti-gt "$OUT/hard/gt" \
    --domain B --seed 1
$SFM_TTR generate --kitti-raw "$OUT/b40/raw" --kitti-gt "$OUT/b40/gt" --frames 40 --domain B \
    --seed 1
HARD=(--kitti-raw "$OUT/hard/raw" --kitti-gt "$OUT/hard/gt" --drive $DRIVE)
B40=(--kitti-raw "$OUT/b40/raw" --kitti-gt "$OUT/b40/gt" --drive $DRIVE)
HOLO=(--images $H/images --intrinsics $H/K.txt --gt-depth $H/depth --gt-scale 1000)

.venv/bin/python scripts/studies/check_outcomes.py "${HARD[@]}" --out "$OUT/hard_outcomes.json"
for seq in hard b40 holo; do
    case $seq in hard) S=("${HARD[@]}");; b40) S=("${B40[@]}");; holo) S=("${HOLO[@]}");; esac
    $SFM_TTR benchmark "${S[@]}" --modes no_ttr sfm_ttr_online --out "$OUT/${seq}_on"
    $SFM_TTR benchmark "${S[@]}" --modes sfm_ttr_online "${OFF[@]}" --out "$OUT/${seq}_off"
done
$SFM_TTR benchmark "${HARD[@]}" --modes sfm_ttr_online --policy continue \
    --out "$OUT/hard_continue_on"
$SFM_TTR benchmark "${HARD[@]}" --modes sfm_ttr_online --policy continue "${OFF[@]}" \
    --out "$OUT/hard_continue_off"
