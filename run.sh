#!/usr/bin/env bash
# Main job: poses the built-in skeleton and writes it (JSON, OpenSim .osim + .mot) to out/demo.
set -euo pipefail
cd "$(dirname "$0")"
source scripts/ensure_venv.sh
exec bodyfit demo --out out/demo "$@"
