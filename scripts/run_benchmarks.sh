#!/usr/bin/env bash
# The benchmark suites recorded in BENCHMARKS.md, default model.
#   bash scripts/run_benchmarks.sh [OUT_DIR]          accuracy (~35 min on 2 CPU cores)
#   bash scripts/run_benchmarks.sh --gpu [OUT_DIR]    the GPU figures (a machine with CUDA, ~6 min)
#
# Accuracy: on ../shared/data/hololens_000 (100 real indoor frames, GT in mm) and on a generated
# KITTI-format drive of held-out domain B (the model was trained on domain A, 40 frames):
# no TTR, what the node gives (node_online: params/kitti.yaml's windows, objective and weight
# policy), the paper's Eq. (5) in the same windows (sfm_ttr_online) and offline in one window
# (sfm_ttr_offline, params/paper.yaml); then the node's live output on hololens_000 at 10 Hz
# and at 1 Hz (the rate its windows keep up with on 2 cores).
#
# GPU: on a generated 90-frame KITTI-size drive, the node's windows and its live output at
# 10 Hz with the network on CUDA and the host held to 2 cores (taskset), the per-window time
# line in live/results.json; one GPU worker's time per sequence on a 3-drive split. (The SfM
# features in torch against pycolmap's SIFT were a study: docs/decisions.md, "Studies".)
# Without pycolmap in its Python (the lent GPU machines), a wheel in out/whl is installed to a
# scratch folder first.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${1:-}" = "--gpu" ]; then
    OUT=${2:-bench_gpu}
    PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
    if ! "$PY" -c "import pycolmap" 2>/dev/null; then
        "$PY" -m pip install -q --no-index --no-deps --target /tmp/sfm_ttr_site out/whl/*.whl
        export PYTHONPATH="/tmp/sfm_ttr_site:$PYTHONPATH"
    fi
    CLI=("$PY" -m sfm_ttr_ros)
    mkdir -p "$OUT"
    "$PY" -c "import torch; print('gpu:', torch.cuda.get_device_name(0))" | tee "$OUT/device.txt"
    for seed in 1 2 3; do
        "${CLI[@]}" generate --kitti-raw "$OUT/data/raw$seed" --kitti-gt "$OUT/data/gt$seed" \
            --frames $([ $seed = 1 ] && echo 90 || echo 30) --domain B --seed $seed
    done
    D1=(--kitti-raw "$OUT/data/raw1" --kitti-gt "$OUT/data/gt1" --drive 2011_09_26_drive_0001_sync)
    # 1. the node's windows and live output on the GPU, the host on 2 cores as on the CPU machine
    PIN=(); command -v taskset >/dev/null && PIN=(taskset -c 0,1)
    "${PIN[@]}" "${CLI[@]}" benchmark "${D1[@]}" --params-file params/kitti.yaml \
        --set device=cuda --modes no_ttr node_online sfm_ttr_live --rate 10 --figure-frames 0 \
        --out "$OUT/live"
    # 2. one GPU worker's time per sequence: a 3-drive split, in process
    {
        for seed in 1 2 3; do
            echo "kitti 2011_09_26_drive_0001_sync raw=data/raw$seed gt=data/gt$seed name=b$seed"
        done
    } > "$OUT/split.txt"
    "${CLI[@]}" benchmark --split "$OUT/split.txt" --params-file params/kitti.yaml \
        --set device=cuda --modes no_ttr node_online --figure-frames 0 --out "$OUT/split"
    exit 0
fi

OUT=${1:-bench}
SFM_TTR=.venv/bin/sfm-ttr
SHARED=../shared/data
NODE=params/kitti.yaml
PAPER=params/paper.yaml

$SFM_TTR generate --kitti-raw "$OUT/data/raw" --kitti-gt "$OUT/data/gt" --frames 40 \
    --domain B --seed 1
B40=(--kitti-raw "$OUT/data/raw" --kitti-gt "$OUT/data/gt" --drive 2011_09_26_drive_0001_sync)
$SFM_TTR benchmark "${B40[@]}" --params-file "$NODE" \
    --modes no_ttr node_online sfm_ttr_online ph_ttr_online --out "$OUT/synthetic_B"
$SFM_TTR benchmark "${B40[@]}" --params-file "$PAPER" --modes sfm_ttr_offline \
    --figure-frames 0 --out "$OUT/synthetic_B_paper_offline"

if [ -d "$SHARED/hololens_000" ]; then
    H=(--images "$SHARED/hololens_000/images" --intrinsics "$SHARED/hololens_000/K.txt"
       --gt-depth "$SHARED/hololens_000/depth" --gt-scale 1000)
    $SFM_TTR benchmark "${H[@]}" --params-file "$NODE" \
        --modes no_ttr node_online sfm_ttr_online ph_ttr_online --out "$OUT/hololens_000"
    $SFM_TTR benchmark "${H[@]}" --params-file "$PAPER" --modes sfm_ttr_offline \
        --figure-frames 0 --out "$OUT/hololens_000_paper_offline"
    for rate in 10 1; do
        $SFM_TTR benchmark "${H[@]}" --params-file "$NODE" --modes sfm_ttr_live --rate $rate \
            --figure-frames 0 --out "$OUT/hololens_000_live_${rate}hz"
    done
else
    echo "run_benchmarks: $SHARED/hololens_000 not found, skipping it" >&2
fi
