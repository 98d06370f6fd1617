#!/usr/bin/env bash
# Prepare the wheelhouse the images install from, so `docker build` needs no network.
#
#   deploy/wheelhouse.sh [DIR]      (default: deploy/.wheelhouse)
#
# Holds swarmrec's own wheel and the wheels of its run-time dependencies (no dev or
# training tools, no torch), pinned by requirements.lock, for CPython 3.11 on
# manylinux x86_64 (the images' platform, whatever the host's). Downloads go
# through pip's cache, so a second run is quick.
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${1:-deploy/.wheelhouse}
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python3

log() { echo "wheelhouse: $*" >&2; }

mkdir -p "$OUT"
rm -f "$OUT"/swarmrec-*.whl
log "building swarmrec's wheel"
# From a copy of what the wheel holds: setuptools stages a build in the source tree (build/,
# swarmrec.egg-info), where a build cut short, or processes of a test run writing beside it,
# failed the next one ("File exists: build/bdist..."). The copy has no such state.
src=$(mktemp -d)
trap 'rm -rf "$src"' EXIT
tar --exclude=__pycache__ -cf - pyproject.toml README.md swarmrec | tar -xf - -C "$src"
# A fixed zip timestamp makes the wheel byte-identical when the code is, so docker reuses its cached layers.
SOURCE_DATE_EPOCH=315532800 "$PY" -m pip wheel --quiet --no-deps --wheel-dir "$OUT" "$src" >/dev/null

# Only the run-time dependencies of pyproject.toml, at the versions of the lock.
reqs=$(mktemp)
trap 'rm -rf "$src" "$reqs"' EXIT
"$PY" - "$reqs" <<'PY'
import sys, tomllib
deps = tomllib.load(open("pyproject.toml", "rb"))["project"]["dependencies"]
open(sys.argv[1], "w").write("\n".join(deps) + "\n")
PY

log "downloading run-time dependencies (cp311, manylinux x86_64)"
"$PY" -m pip download --quiet --dest "$OUT" --requirement "$reqs" --constraint requirements.lock \
  --only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 --platform linux_x86_64 --platform any
log "$(ls "$OUT" | wc -l) wheels, $(du -sh "$OUT" | cut -f1) in $OUT"
