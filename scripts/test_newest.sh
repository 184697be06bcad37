#!/usr/bin/env bash
# Runs the test suite against the newest releases that pyproject.toml allows, not the lock's: a throwaway
# environment in build/newest-venv (torch stays 2.13.0, CPU build), then pytest. Use it before refreshing
# the lock (scripts/lock.sh) to see what a newer dependency breaks; the installed versions are printed
# first and written to build/newest-versions.txt.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
venv="$root/build/newest-venv"
rm -rf "$venv"
python3 -m venv "$venv"
torch_pin="$(grep -o '"torch==[^"]*"' pyproject.toml | head -1 | tr -d '"')"
"$venv/bin/python" -m pip install --quiet --upgrade pip
if ! "$venv/bin/python" -m pip install --quiet --no-index "${torch_pin}+cpu" 2>/dev/null; then
    "$venv/bin/python" -m pip install --quiet \
        --index-url "${BODYFIT_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}" "${torch_pin}+cpu"
fi
"$venv/bin/python" -m pip install --quiet --upgrade --upgrade-strategy eager "${torch_pin}+cpu" \
    -e "$root[server,build,dev,ray,grpc]"
"$venv/bin/python" -m pip freeze --exclude-editable | tee build/newest-versions.txt | \
    grep -iE '^(numpy|scipy|onnxruntime|trimesh|fastapi|grpcio|pydantic|torch)=='
export WARP_CACHE_PATH="$root/build/cache/warp" ANNY_CACHE_DIR="$root/build/cache/anny"
export XDG_CACHE_HOME="$root/build/cache"
exec "$venv/bin/python" -m pytest -q -n 2 "$@"
