#!/usr/bin/env bash
# Creates .venv on first use (or when the lock changed) with exactly the versions of requirements/lock.txt,
# every file checked against the lock's sha256 hashes, then bodyfit itself (editable, no dependencies).
# torch is the CPU build (torch==2.13.0+cpu): taken from a local wheel folder that pip is configured with when
# there is one, else from PyTorch's CPU index ($BODYFIT_TORCH_INDEX). The lock is refreshed by
# scripts/lock.sh, never by installing.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
lock="$root/requirements/lock.txt"
stamp="$venv/.bodyfit-installed"
want="$(cat "$root/pyproject.toml" "$lock" | sha256sum | cut -d' ' -f1)"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    # (pip_quiet drops pip's notes about configured index folders that do not hold a package)
    pip_quiet() { "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }
    echo "bodyfit: installing the locked environment into $venv (first run: several minutes)" >&2
    pip=(pip_quiet "$venv/bin/python" -m pip --disable-pip-version-check)
    # torch first, on its own: its CPU build is not on PyPI. Its lines of the lock carry its hash.
    # (no temporary file: this script is sourced by scripts that exec, so an EXIT trap would never run)
    torch_req="$(awk '/^torch==/{on=1} on{print; if ($0 !~ /\\$/) exit}' "$lock")"
    if ! "${pip[@]}" install --quiet --no-deps --require-hashes --no-index \
        -r <(printf '%s\n' "$torch_req") 2>/dev/null; then
        "${pip[@]}" install --quiet --no-deps --require-hashes \
            --index-url "${BODYFIT_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}" \
            -r <(printf '%s\n' "$torch_req")
    fi
    "${pip[@]}" install --quiet --no-deps --require-hashes -r "$lock"
    "${pip[@]}" install --quiet --no-deps --no-build-isolation -e "$root"
    echo "$want" > "$stamp"
fi
# Caches of build-time tools stay inside the project's ignored build folder.
export WARP_CACHE_PATH="$root/build/cache/warp"
export ANNY_CACHE_DIR="$root/build/cache/anny"
export XDG_CACHE_HOME="$root/build/cache"
export PATH="$venv/bin:$PATH"
