#!/usr/bin/env bash
# Refreshes the lock: resolves the newest releases that pyproject.toml allows (torch stays 2.13.0, CPU build),
# writes requirements/lock.txt (every extra, with sha256 hashes) and the image's subsets derived from it
# (requirements/server.txt, requirements/ray.txt: same versions), rebuilds .venv from the new lock and runs
# the whole suite. Review `git diff requirements/`, and commit the lock only with a passing suite.
#   scripts/lock.sh                        refresh every package
#   scripts/lock.sh --upgrade-package X    refresh X alone (repeatable; the rest keeps its pins)
#   scripts/lock.sh --no-test ...          write the lock files only
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
run_tests=1
args=()
for a in "$@"; do
    if [ "$a" = "--no-test" ]; then run_tests=0; else args+=("$a"); fi
done
[ ${#args[@]} -eq 0 ] && args=(--upgrade)

tools="$root/build/lock-tools"
if [ ! -x "$tools/bin/pip-compile" ]; then
    python3 -m venv "$tools"
    "$tools/bin/python" -m pip install --quiet "pip-tools==7.7.0"
fi
# torch's CPU build is not on PyPI: use a local wheel folder pip already knows of, else PyTorch's CPU index.
torch_pin="$(grep -o '"torch==[^"]*"' pyproject.toml | head -1 | tr -d '"')"
sources=()
probe="$(mktemp -d)"
trap 'rm -rf "$probe"' EXIT
if ! "$tools/bin/python" -m pip download --quiet --no-deps --no-index -d "$probe" "${torch_pin}+cpu" 2>/dev/null; then
    sources=(--extra-index-url "${BODYFIT_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}")
fi
compile() {  # compile OUT EXTRAS [pip-compile options]
    local out="$1" extras="$2"
    shift 2
    CUSTOM_COMPILE_COMMAND="scripts/lock.sh" "$tools/bin/pip-compile" --quiet --generate-hashes \
        --allow-unsafe --strip-extras --no-emit-index-url --no-emit-find-links --extra "$extras" \
        "${sources[@]}" --output-file "$out" "$@" pyproject.toml
}
compile requirements/lock.txt server,build,dev,ray,grpc "${args[@]}"
# The image's subsets take their versions from the full lock (a constraint without hashes).
pins=build/lock-pins.txt
sed -e 's/ *\\$//' -e '/^ *--hash/d' -e '/^ *#/d' -e '/^$/d' requirements/lock.txt > "$pins"
compile requirements/server.txt server --upgrade -c "$pins"
compile requirements/ray.txt server,ray --upgrade -c "$pins"
echo "lock written: $(grep -c '^[A-Za-z0-9].*==' requirements/lock.txt) packages" >&2
if [ "$run_tests" = 1 ]; then
    ./test.sh
fi
