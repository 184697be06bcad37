#!/usr/bin/env bash
# Regenerates the gRPC modules from bodyfit/api/bodyfit.proto (needs grpcio-tools, in the dev extra).
# Usage: scripts/gen_proto.sh [OUT_DIR]   (default: bodyfit/api, next to the .proto)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
out="${1:-$root/bodyfit/api}"
python="${PYTHON:-$root/.venv/bin/python}"
"$python" -m grpc_tools.protoc -I "$root/bodyfit/api" --python_out="$out" --pyi_out="$out" \
    --grpc_python_out="$out" "$root/bodyfit/api/bodyfit.proto"
# The generated service module imports its messages as a top-level module; make it package-relative.
sed -i 's/^import bodyfit_pb2 as bodyfit__pb2$/from . import bodyfit_pb2 as bodyfit__pb2/' "$out/bodyfit_pb2_grpc.py"
