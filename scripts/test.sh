#!/usr/bin/env bash
# Run the test suite (CPU only) in the project's virtual environment, set up first if needed; the linter and the
# type checker first (scripts/lint.sh: a finding fails the run before any test).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/lint.sh
exec .venv/bin/python -m pytest -n 2 -q "$@"
