#!/usr/bin/env bash
# Lint and type check, configured in pyproject.toml: ruff (pyflakes, pycodestyle, bugbear; 120 columns) on the
# whole tree, then mypy on dsr_bench, generators and annotator. Fails on the first tool with findings.
# scripts/test.sh (and so CI) runs it before the tests; the tools come from the project's install
# (scripts/setup.sh, the `lint` extra of pyproject.toml).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check --quiet .
.venv/bin/mypy
