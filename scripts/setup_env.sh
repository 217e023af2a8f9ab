#!/usr/bin/env bash
# Create (or refresh) the project's virtual environment in .venv and install the package into it
# editable, with the ROS 2 Jazzy wheels, the development tools, the training extra, the
# Hugging Face extra (transformers, peft) and the cluster extra (Ray, tqdm: docs/cluster.md).
# Idempotent: a second run only checks that everything is there.
#
#   bash scripts/setup_env.sh          # or: make setup
#   PYTHON=python3.12 bash scripts/setup_env.sh
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${VENV:-$ROOT/.venv}"
TORCH_VERSION="2.13.0"
# colcon needs setuptools < 80; torch 2.13 needs >= 77.0.3. Passed to every pip call below so
# that no step upgrades it.
SETUPTOOLS="setuptools>=77.0.3,<80"

say() { printf '[setup_env] %s\n' "$*"; }

if [[ -z "${PYTHON:-}" ]]; then
    if command -v python3.11 >/dev/null 2>&1; then PYTHON=python3.11; else PYTHON=python3; fi
fi

if [[ ! -x "$VENV/bin/python" ]]; then
    say "creating virtual environment $VENV with $($PYTHON --version 2>&1) ($PYTHON)"
    "$PYTHON" -m venv "$VENV"
else
    say "virtual environment $VENV exists ($("$VENV/bin/python" --version 2>&1))"
fi
PY="$VENV/bin/python"
PIP=("$PY" -m pip --disable-pip-version-check)

# Stamp: skip the pip work when nothing that drives the install changed since the last success.
STAMP="$VENV/.sfm_ttr_ros_setup_stamp"
INPUTS_HASH="$(cat setup.py setup.cfg package.xml requirements.txt sfm_ttr_ros/requirements.py \
    scripts/setup_env.sh \
    | sha256sum | cut -d' ' -f1)"
if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$INPUTS_HASH" ]] \
        && (cd / && "$PY" -c "import torch, pycolmap, sfm_ttr_ros" >/dev/null 2>&1); then
    say "up to date (delete $STAMP to force a reinstall)"
    exit 0
fi

say "upgrading pip"
"${PIP[@]}" install --upgrade pip

say "installing build tools: $SETUPTOOLS and wheel"
"${PIP[@]}" install "$SETUPTOOLS" wheel

# torch first and pinned: this machine has the CPU wheel of torch $TORCH_VERSION on disk; with no
# torch installed, the package's loose `torch>=2.1` would pull a multi-GB CUDA build.
say "installing torch==$TORCH_VERSION first"
"${PIP[@]}" install "torch==$TORCH_VERSION" "$SETUPTOOLS"

# --no-build-isolation: build with the setuptools just installed instead of fetching the
# newest setuptools into an isolated build environment.
say "installing sfm_ttr_ros editable with extras ros,dev,train,hf,cluster"
"${PIP[@]}" install --no-build-isolation -e ".[ros,dev,train,hf,cluster]" "$SETUPTOOLS"

say "checking the environment"
(cd / && "$PY" - <<'PYEOF'
import pycolmap
import torch

import sfm_ttr_ros

print(f"[setup_env] python ok: torch {torch.__version__}, pycolmap {pycolmap.__version__}, "
      f"sfm_ttr_ros {sfm_ttr_ros.__version__} from {sfm_ttr_ros.__file__}")
PYEOF
)

echo "$INPUTS_HASH" > "$STAMP"
say "done: activate with 'source .venv/bin/activate', or use .venv/bin/... directly"
