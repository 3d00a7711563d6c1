#!/usr/bin/env bash
# Set up pocoloco on a fresh CPU machine: a .venv with the CPU build of PyTorch,
# pocoloco itself (editable) with its data-synthesis and test extras, and the one
# system library open3d needs. Safe to rerun.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) >/dev/null
  else
    echo "setup: please install libusb-1.0-0 (needed by open3d)" >&2
  fi
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
pip install -q --disable-pip-version-check --upgrade pip 2>&1 | grep -v -i warning || true
# CPU build first: a bare `torch` requirement would pull a multi-GB CUDA build.
python -c "import torch" 2>/dev/null || pip install -q --disable-pip-version-check torch==2.13.0 2>&1 | grep -v -i warning || true
pip install -q --disable-pip-version-check -e ".[dev]" 2>&1 | grep -v -i warning || true
python -c "import pocoloco, torch, anny, newton, open3d" 2>/dev/null || { echo "setup: import check failed" >&2; python -c "import pocoloco, torch, anny, newton, open3d"; }
echo "setup: ok ($(python -c 'import torch; print("torch", torch.__version__)'))"
