#!/usr/bin/env bash
# Lint, check the formatting, type-check, build the documentation site (strict: a broken link or reference fails) and run the
# whole test suite.
set -euo pipefail
cd "$(dirname "$0")"
source scripts/ensure_venv.sh
ruff check .
ruff format --check .
mypy
mkdocs build --strict --quiet --site-dir build/site
exec python -m pytest -q -n 2 "$@"
