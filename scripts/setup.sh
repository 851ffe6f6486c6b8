#!/usr/bin/env bash
# Set up dsr-bench on a fresh machine: system library for open3d, a virtual environment in .venv,
# the CPU build of torch (pinned: an unpinned torch pulls a multi-GB CUDA build), and the package.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so"; then
  if [ "$(id -u)" = 0 ]; then
    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null) \
      || echo "warning: could not install libusb-1.0-0; open3d (generator, annotator) will not import" >&2
  else
    echo "warning: libusb-1.0-0 is missing; run: sudo apt-get install -y libusb-1.0-0" >&2
  fi
fi
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[all]"
echo "dsr-bench installed in .venv ($(.venv/bin/dsr-bench --version))" >&2
