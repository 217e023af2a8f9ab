#!/usr/bin/env bash
# The refinement step captured as one CUDA graph and the batched torch SIFT, measured on a lent
# GPU in ONE command of about 5 minutes (each part under its own time limit, all of them under
# ~7.5 min), every result as JSON under $OUT (docs/decisions.md "The refinement step on CUDA:
# captured as one graph"; what it measures: scripts/README.md).
#
#   bash scripts/gpu_window_check.sh                # on the GPU machine: OUT=$OUT or gpu_check
#   bash scripts/gpu_window_check.sh --cpu-dry-run  # every part, tiny sizes, on the CPU
#
# (a) pycolmap: the GPU machines' image has torch, opencv, numpy and transformers but not
#     pycolmap; a wheel in out/whl (git-ignored; carried to the machine) is unpacked to a
#     scratch folder and put on PYTHONPATH:
#       .venv/bin/pip download pycolmap==4.2.1 --python-version 3.12 --only-binary=:all: \
#           --platform manylinux_2_28_x86_64 --no-deps -d out/whl
#     (a pycolmap*.tar.xz of the unpacked wheel is taken as well)
# (b) a generated 30-frame KITTI-size drive (domain B, seed 1);
# (c) profile.json: one 15-frame window, eager against the graph under torch.profiler, and
#     the step micro-benchmark (200 steps, Eq. (5) at 600 points); timing.json: the same
#     window without the profiler and its SfM with pycolmap's SIFT against the batched torch
#     SIFT; bench_graph/: `sfm-ttr benchmark --modes node_online sfm_ttr_live --set
#     device=cuda` (step_mode auto: the graph; live at 3 Hz); bench_eager/: node_online with
#     step_mode eager;
# (d) parts.jsonl: each part's exit status and seconds; check.json: all of it in short
#     (sfm_ttr_ros/tools/step_profile.py check_summary); summary.txt: the lines people read.
set -uo pipefail
cd "$(dirname "$0")/.."

DRY=0
[ "${1:-}" = "--cpu-dry-run" ] && DRY=1
OUT=${OUT:-gpu_check}
mkdir -p "$OUT"
PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
DEADLINE=${GPU_CHECK_SECONDS:-450}  # all parts end by then (the device allows 600 s a command)
: > "$OUT/parts.jsonl"
: > "$OUT/summary.txt"

# (a) pycolmap from a carried wheel (unpacked even when pycolmap imports: the dry run checks it)
SITE=${SFM_TTR_SITE:-/tmp/sfm_ttr_site}
for f in out/whl/pycolmap*.whl out/whl/pycolmap*.tar.xz; do
    [ -f "$f" ] || continue
    mkdir -p "$SITE"
    case "$f" in
        *.whl) "$PY" -m zipfile -e "$f" "$SITE" ;;
        *.tar.xz) tar -xJf "$f" -C "$SITE" ;;
    esac
    echo "unpacked $f to $SITE" >> "$OUT/summary.txt"
done
if ! "$PY" -c "import pycolmap" 2>/dev/null; then
    export PYTHONPATH="$SITE:$PYTHONPATH"
fi

# part NAME LIMIT_S COMMAND...: run it under the smaller of LIMIT_S and the time left
part() {
    local name=$1 limit=$2 left rc t0
    shift 2
    left=$(( DEADLINE - SECONDS ))
    [ "$left" -lt "$limit" ] && limit=$left
    if [ "$limit" -le 5 ]; then
        echo "{\"part\": \"$name\", \"rc\": null, \"skipped\": \"no time left\"}" >> "$OUT/parts.jsonl"
        return 0
    fi
    t0=$SECONDS
    timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
    rc=$?
    echo "{\"part\": \"$name\", \"rc\": $rc, \"seconds\": $(( SECONDS - t0 )), \"limit\": $limit}" \
        >> "$OUT/parts.jsonl"
    echo "== $name: rc $rc, $(( SECONDS - t0 )) s" >> "$OUT/summary.txt"
    grep -v '^USDT' "$OUT/$name.log" | tail -n 12 >> "$OUT/summary.txt"
}

"$PY" - > "$OUT/device.json" <<'EOF'
import json, os, torch
print(json.dumps({"torch": torch.__version__, "cuda": torch.cuda.is_available(),
                  "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
                  "host_cores": os.cpu_count()}))
EOF

if [ "$DRY" = 1 ]; then
    FRAMES=16; SIZE=(--width 416 --height 128); WINDOW=4; MICRO=6; POINTS=100
    DEVICE=cpu
    SETS=(--set device=cpu --set window_size=4 --set window_stride=2 --set refinement.steps=6
          --set min_supervision_points=20 --set sfm.max_num_features=2048
          --set model.input_height=96 --set model.input_width=320 --set torch_num_threads=1)
else
    FRAMES=30; SIZE=(); WINDOW=15; MICRO=200; POINTS=600
    DEVICE=cuda
    SETS=(--set device=cuda)
fi
# the drive lives outside $OUT: what is under $OUT comes back from the device machine
DATA=${GPU_CHECK_DATA:-${TMPDIR:-/tmp}/sfm_ttr_gpu_check}
rm -rf "$DATA"
D=(--kitti-raw "$DATA/raw" --kitti-gt "$DATA/gt" --drive 2011_09_26_drive_0001_sync)
CLI=("$PY" -m sfm_ttr_ros)
PROFILE=("$PY" scripts/profile_refinement.py --kitti-raw "$DATA/raw" --window "$WINDOW"
         "${SETS[@]}")

# (b) the drive
part generate 120 "${CLI[@]}" generate --kitti-raw "$DATA/raw" --kitti-gt "$DATA/gt" \
    --frames "$FRAMES" "${SIZE[@]}" --domain B --seed 1
# (c) eager against the graph, under the profiler, and the step micro-benchmark
part profile 150 "${PROFILE[@]}" --modes eager auto --micro-steps "$MICRO" \
    --micro-points "$POINTS" --out "$OUT/profile.json"
# the node's windows and live output with the graph (step_mode auto on CUDA); the live feed at
# 3 Hz: 30 frames last 10 s, so that the first window ends before the feed does (the end of
# the feed cancels a running window)
part bench_graph 150 "${CLI[@]}" benchmark "${D[@]}" "${SETS[@]}" \
    --modes node_online sfm_ttr_live --rate 3 --figure-frames 0 --out "$OUT/bench_graph"
# the same window timed without the profiler; its SfM with pycolmap's and the torch SIFT
part timing 120 "${PROFILE[@]}" --modes eager auto --no-profile \
    --sfm-features colmap torch --out "$OUT/timing.json"
# the node's windows with the eager step, for the comparison
part bench_eager 90 "${CLI[@]}" benchmark "${D[@]}" "${SETS[@]}" \
    --set refinement.step_mode=eager --modes node_online --figure-frames 0 \
    --out "$OUT/bench_eager"

"$PY" -c "import sys; from sfm_ttr_ros.tools.step_profile import write_check_summary as w; \
print(w(sys.argv[1]))" "$OUT" >> "$OUT/summary.txt" 2>&1
echo "done in $SECONDS s (device $DEVICE); parts: $OUT/parts.jsonl" >> "$OUT/summary.txt"
cat "$OUT/summary.txt"
