#!/usr/bin/env bash
# Set up dsr-bench on a fresh machine: system library for open3d, a virtual environment in .venv,
# the CPU build of torch (pinned: an unpinned torch pulls a multi-GB CUDA build), and the package.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/apt_install.sh  # apt_install: waits for the dpkg lock, and shows apt's reason when it fails
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so"; then
  if [ "$(id -u)" = 0 ]; then
    apt_install "could not install libusb-1.0-0; open3d (generator, annotator) will not import" libusb-1.0-0 \
      || true
  else
    echo "warning: libusb-1.0-0 is missing; run: sudo apt-get install -y libusb-1.0-0" >&2
  fi
fi
# The annotator window and its test: a virtual X display (xvfb-run needs xauth) and Mesa's OpenGL, with which
# open3d's legacy visualizer renders under `xvfb-run` (GLX through swrast; EGL for open3d's offscreen fallback);
# xdotool lets the test type real keys into the window. qemu-user runs the generator on an emulated AVX2-only
# CPU for the cross-instruction-set reproducibility test (tests/test_reproducibility.py; it skips without).
WINDOW_PKGS="xvfb xauth libgl1 libglx-mesa0 libgl1-mesa-dri libegl1 libegl-mesa0 xdotool qemu-user"
if command -v dpkg >/dev/null 2>&1; then
  missing=""
  for pkg in $WINDOW_PKGS; do dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"; done
  if [ -n "$missing" ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      # shellcheck disable=SC2086  # one word per package
      apt_install "could not install$missing; the annotator window needs a display (its test skips)" $missing \
        || true
    else
      echo "warning:$missing missing; for the annotator window run: sudo apt-get install -y$missing" >&2
    fi
  fi
elif ! command -v xvfb-run >/dev/null 2>&1; then
  echo "warning: no apt here; install Xvfb and Mesa OpenGL for the annotator window's test (it skips otherwise)" >&2
fi
# The leaderboard page's browser test (tests/test_leaderboard.py) renders a built index.html in headless Chromium
# and looks at it (tables, bold, links, plots, sorting by a click); it skips when no Chromium binary is found.
have_chromium=""
for browser in chromium chromium-browser chromium-headless-shell google-chrome google-chrome-stable; do
  if command -v "$browser" >/dev/null 2>&1; then have_chromium=1; fi
done
if [ -z "$have_chromium" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    apt_install "could not install chromium; the leaderboard page's browser test skips" chromium || true
  else
    echo "note: no Chromium; for the leaderboard page's browser test run: sudo apt-get install -y chromium" >&2
  fi
fi
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
# every other package at the version the suite last passed with (scripts/constraints.txt: the bit-for-bit pins of the
# splits, objects and plans hold across machines on the same numpy, scipy, pybullet ...)
.venv/bin/python -m pip install -q "torch==2.13.0" -c scripts/constraints.txt
.venv/bin/python -m pip install -q -e ".[all]" -c scripts/constraints.txt
echo "dsr-bench installed in .venv ($(.venv/bin/dsr-bench --version))" >&2
