#!/usr/bin/env bash
# Set up Endoscopic Chisel on a fresh Debian machine (run as root, or with sudo available):
# system libraries, a virtual environment at .venv, and the package with its dev tools.
# Idempotent: a second run only checks what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi

# libusb-1.0-0: Open3D's wheel links it at import.
# libllvm19: drjit 1.5 (Mitsuba 3.9) aborts with the system LLVM 15; LLVM 19 works.
# chromium: the workflow report test opens the HTML report headless.
# chromium-driver: the report test drives it with selenium to read the browser console.
# slurm-wlm, munge: scripts/slurm-local.sh starts a single-node SLURM cluster from them
#   (tests/test_slurm.py runs the smoke experiment through it); Debian 12: SLURM 22.05.
need=()
for pkg in libusb-1.0-0 libllvm19 chromium chromium-driver slurm-wlm munge; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ "${#need[@]}" -gt 0 ]; then
  echo "setup: installing system packages: ${need[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# CPU build of torch first: a bare requirement would pull several GB of CUDA packages.
if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  .venv/bin/pip install -q torch==2.13.0
fi
.venv/bin/pip install -q -e ".[dev]"
.venv/bin/python -c "import open3d, mitsuba, manifold3d, torch, numba; print('setup: ok, torch', torch.__version__)"
