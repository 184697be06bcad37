#!/usr/bin/env bash
# Main job: serves the built-in model over REST (http://127.0.0.1:8000, OpenAPI at /docs) and gRPC
# (127.0.0.1:50051). Options are passed on: ./run.sh --port 9000 --grpc-port 0 (see `bodyfit serve --help`).
set -euo pipefail
cd "$(dirname "$0")"
source scripts/ensure_venv.sh
exec bodyfit serve "$@"
