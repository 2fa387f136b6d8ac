#!/usr/bin/env bash
# Install what pivla needs on a fresh Debian machine: system packages (rendering, AVR toolchain, simavr),
# then .venv with the package and its extras. Idempotent: re-running installs only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS="${PIVLA_EXTRAS:-all,dev}"
APT_PACKAGES=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libglfw3
              gcc-avr avr-libc binutils-avr simavr libsimavr-dev arduino-core-avr libelf-dev pkg-config)

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
  echo "setup: installing Debian packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY="${PYTHON:-python3}"
if [[ ! -x .venv/bin/python ]]; then
  "$PY" -m venv .venv
fi
# torch first and pinned: the CPU wheel (no CUDA, no torchvision)
.venv/bin/pip install -q "torch==2.13.0"
.venv/bin/pip install -q -e ".[${EXTRAS}]"
echo "setup: .venv ready ($(.venv/bin/python -c 'import torch, mujoco; print("torch", torch.__version__, "mujoco", mujoco.__version__)'))"
