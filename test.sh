#!/usr/bin/env bash
# Lint, type-check and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")"
source scripts/ensure_venv.sh
ruff check .
mypy
exec python -m pytest -q -n 2 "$@"
