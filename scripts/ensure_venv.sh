#!/usr/bin/env bash
# Creates .venv on first use (or when pyproject.toml changed) with the CPU build of torch pinned.
# anny and nimblephysics depend on an unpinned torch: they are installed in the same pip command as
# torch==2.13.0 so pip keeps the CPU build.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
stamp="$venv/.bodyfit-installed"
want="$(sha256sum "$root/pyproject.toml" | cut -d' ' -f1)"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    "$venv/bin/python" -m pip install --quiet --upgrade pip
    "$venv/bin/python" -m pip install --quiet "torch==2.13.0" -e "$root[server,build,dev]"
    echo "$want" > "$stamp"
fi
# Caches of build-time tools stay inside the project's ignored build folder.
export WARP_CACHE_PATH="$root/build/cache/warp"
export ANNY_CACHE_DIR="$root/build/cache/anny"
export XDG_CACHE_HOME="$root/build/cache"
export PATH="$venv/bin:$PATH"
