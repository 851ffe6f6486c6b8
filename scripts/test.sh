#!/usr/bin/env bash
# Run the test suite (CPU only) in the project's virtual environment, set up first if needed; the linter and the
# type checker first (scripts/lint.sh: a finding fails the run before any test).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The challenge server's tests (tests/test_challenge_*.py) run its database tests against a throwaway PostgreSQL
# cluster (initdb + pg_ctl) and watch its pages in chromium through chromium-driver; each skips, saying why, where
# they are missing.
source scripts/apt_install.sh
system_pkgs=""
ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || command -v initdb >/dev/null 2>&1 || system_pkgs="postgresql"
command -v chromedriver >/dev/null 2>&1 || system_pkgs="$system_pkgs chromium-driver"
# The viewer's screenshot test (tests/test_viewer_screenshot.py) renders the real rerun viewer under Xvfb with Mesa's
# software Vulkan (lavapipe); it skips, saying why, where they are missing.
command -v xvfb-run >/dev/null 2>&1 || system_pkgs="$system_pkgs xvfb xauth"
ls /usr/share/vulkan/icd.d/lvp_icd.*.json >/dev/null 2>&1 || system_pkgs="$system_pkgs mesa-vulkan-drivers"
if [ -n "$system_pkgs" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    # shellcheck disable=SC2086  # one word per package
    apt_install "could not install$system_pkgs; the tests that need them skip" \
      $system_pkgs || true
  else
    echo "note: for the challenge's PostgreSQL and browser tests and the viewer's screenshot test run:" \
      "sudo apt-get install -y $system_pkgs" >&2
  fi
fi
bash scripts/lint.sh
exec .venv/bin/python -m pytest -n 2 -q "$@"
