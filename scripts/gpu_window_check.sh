#!/usr/bin/env bash
# The refinement step captured as one CUDA graph, live serving beside it and the batched torch
# SIFT, measured on a lent GPU in ONE command of at most ~7.5 min (each part under its own time
# limit, the limits adding up to 420 s against a 450-s deadline), every result as JSON under
# $OUT, written as each part goes (docs/decisions.md "The refinement step on CUDA: captured as
# one graph"; what it measures: scripts/README.md).
#
#   bash scripts/gpu_window_check.sh                # on the GPU machine: OUT=$OUT or gpu_check
#   bash scripts/gpu_window_check.sh --cpu-dry-run  # every part, tiny sizes, on the CPU (CI)
#
# (a) pycolmap: the GPU machines' image has torch, opencv, numpy and transformers but not
#     pycolmap; a wheel in out/whl (git-ignored; carried to the machine) is unpacked to a
#     scratch folder and put on PYTHONPATH:
#       .venv/bin/pip download pycolmap==4.2.1 --python-version 3.12 --only-binary=:all: \
#           --platform manylinux_2_28_x86_64 --no-deps -d out/whl
#     (a pycolmap*.tar.xz of the unpacked wheel is taken as well)
# (b) a generated 30-frame KITTI-size drive (domain B, seed 1);
# (c) profile.json: one 15-frame window, eager against the graph under torch.profiler, the
#     same window refined 10 times with the kept graph (capture cost per window, memory
#     reserved after 2 and 10 windows) and the step micro-benchmark (200 steps, Eq. (5) at 600
#     points); bench_graph/, bench_eager/: `sfm-ttr benchmark --modes node_online
#     sfm_ttr_live` on the drive with step_mode auto (the graph) and eager, live at 3 Hz;
#     holo_graph/, holo_eager/: the same on hololens_000 (real video,
#     ../shared/data/hololens_000) at 10 Hz; timing.json: the window without the profiler and
#     its SfM with pycolmap's SIFT against the batched torch SIFT (seconds per stage); SfM with
#     as many threads as the host has cores (nproc);
# (d) parts.jsonl: each part's start, exit status and seconds; check.json: all of it in short
#     (sfm_ttr_ros/tools/step_profile.py check_summary); figures.md: the figures' table
#     (sfm_ttr_ros/tools/gpu_check.py); summary.txt: the lines people read.
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
    echo "{\"part\": \"$name\", \"started\": $t0, \"limit\": $limit}" >> "$OUT/parts.jsonl"
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

CORES=$(nproc 2>/dev/null || echo 2)
HOLO=${HOLOLENS:-../shared/data/hololens_000}
for h in "$HOLO" shared/data/hololens_000 ../../shared/data/hololens_000; do
    [ -d "$h/images" ] && { HOLO=$h; break; }
done
if [ "$DRY" = 1 ]; then
    FRAMES=14; SIZE=(--width 320 --height 96); WINDOW=4; MICRO=5; POINTS=50; WINDOWS=3
    HOLO_FRAMES=8; DEVICE=cpu
    SETS=(--set device=cpu --set window_size=4 --set window_stride=4 --set refinement.steps=5
          --set min_supervision_points=20 --set sfm.max_num_features=1024
          --set model.input_height=64 --set model.input_width=192 --set torch_num_threads=1
          --set sfm.num_threads="$CORES")
else
    FRAMES=30; SIZE=(); WINDOW=15; MICRO=200; POINTS=600; WINDOWS=10
    HOLO_FRAMES=60; DEVICE=cuda
    SETS=(--set device=cuda --set sfm.num_threads="$CORES")
fi
# the drive lives outside $OUT: what is under $OUT comes back from the device machine
DATA=${GPU_CHECK_DATA:-${TMPDIR:-/tmp}/sfm_ttr_gpu_check}
rm -rf "$DATA"
D=(--kitti-raw "$DATA/raw" --kitti-gt "$DATA/gt" --drive 2011_09_26_drive_0001_sync)
H=(--images "$HOLO/images" --intrinsics "$HOLO/K.txt" --gt-depth "$HOLO/depth" --gt-scale 1000
   --max-frames "$HOLO_FRAMES")
CLI=("$PY" -m sfm_ttr_ros)
PROFILE=("$PY" scripts/profile_refinement.py --kitti-raw "$DATA/raw" --window "$WINDOW"
         "${SETS[@]}")
LIVE=(--modes node_online sfm_ttr_live --figure-frames 0)

# (b) the drive
part generate 40 "${CLI[@]}" generate --kitti-raw "$DATA/raw" --kitti-gt "$DATA/gt" \
    --frames "$FRAMES" "${SIZE[@]}" --domain B --seed 1
# (c) eager against the graph under the profiler, the kept graph over windows, the step
# micro-benchmark (profile.json rewritten after each)
part profile 100 "${PROFILE[@]}" --modes eager auto --windows "$WINDOWS" \
    --micro-steps "$MICRO" --micro-points "$POINTS" --out "$OUT/profile.json"
# the node's windows and live output, graph then eager; the live feed at 3 Hz: 30 frames last
# 10 s, so that the first window ends before the feed does (its end cancels a running window)
part bench_graph 70 "${CLI[@]}" benchmark "${D[@]}" "${SETS[@]}" "${LIVE[@]}" --rate 3 \
    --out "$OUT/bench_graph"
part bench_eager 60 "${CLI[@]}" benchmark "${D[@]}" "${SETS[@]}" "${LIVE[@]}" --rate 3 \
    --set refinement.step_mode=eager --out "$OUT/bench_eager"
# real video at 10 Hz, graph then eager
if [ -d "$HOLO/images" ]; then
    part holo_graph 60 "${CLI[@]}" benchmark "${H[@]}" "${SETS[@]}" "${LIVE[@]}" --rate 10 \
        --out "$OUT/holo_graph"
    part holo_eager 50 "${CLI[@]}" benchmark "${H[@]}" "${SETS[@]}" "${LIVE[@]}" --rate 10 \
        --set refinement.step_mode=eager --out "$OUT/holo_eager"
else
    echo "{\"part\": \"holo\", \"rc\": null, \"skipped\": \"no $HOLO\"}" >> "$OUT/parts.jsonl"
fi
# the window timed without the profiler; its SfM with pycolmap's and the torch SIFT
part timing 40 "${PROFILE[@]}" --modes eager auto --no-profile \
    --sfm-features colmap torch --out "$OUT/timing.json"

"$PY" -c "import sys; from sfm_ttr_ros.tools.step_profile import write_check_summary as w; \
print(w(sys.argv[1]))" "$OUT" >> "$OUT/summary.txt" 2>&1
cat "$OUT/figures.md" >> "$OUT/summary.txt" 2>/dev/null
echo "done in $SECONDS s (device $DEVICE, $CORES cores); parts: $OUT/parts.jsonl" >> "$OUT/summary.txt"
cat "$OUT/summary.txt"
