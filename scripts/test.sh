#!/usr/bin/env bash
# Run the test suite (CPU only) in the project's virtual environment, set up first if needed.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -n 2 -q "$@"
