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
challenge_pkgs=""
ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || command -v initdb >/dev/null 2>&1 || challenge_pkgs="postgresql"
command -v chromedriver >/dev/null 2>&1 || challenge_pkgs="$challenge_pkgs chromium-driver"
if [ -n "$challenge_pkgs" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    # shellcheck disable=SC2086  # one word per package
    apt_install "could not install$challenge_pkgs; the challenge's PostgreSQL or browser tests skip" \
      $challenge_pkgs || true
  else
    echo "note: for the challenge's PostgreSQL and browser tests run: sudo apt-get install -y $challenge_pkgs" >&2
  fi
fi
bash scripts/lint.sh
exec .venv/bin/python -m pytest -n 2 -q "$@"
