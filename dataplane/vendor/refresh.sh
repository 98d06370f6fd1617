#!/usr/bin/env bash
# Replace the vendored x86-simd-sort with the copy a numpy release ships
# (dataplane/vendor/README.md says why). Usage: dataplane/vendor/refresh.sh 2.4.6
set -euo pipefail
version=${1:?usage: $0 <numpy version>}
here=$(cd "$(dirname "$0")" && pwd)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
url=$(curl -fsSL https://pypi.org/simple/numpy/ | grep -o "href=\"[^\"]*numpy-${version}.tar.gz[^\"]*\"" | head -1 | sed 's/^href="//; s/"$//')
[ -n "$url" ] || { echo "numpy ${version}: no source distribution on PyPI" >&2; exit 1; }
curl -fsSL -o "$tmp/numpy.tar.gz" "${url%%#*}"
echo "numpy-${version}.tar.gz sha256 $(sha256sum "$tmp/numpy.tar.gz" | cut -d' ' -f1)"
tar -xzf "$tmp/numpy.tar.gz" -C "$tmp" "numpy-${version}/numpy/_core/src/npysort/x86-simd-sort"
src="$tmp/numpy-${version}/numpy/_core/src/npysort/x86-simd-sort"
rm -rf "$here/x86-simd-sort"
mkdir -p "$here/x86-simd-sort/src"
cp "$src/LICENSE.md" "$here/x86-simd-sort/"
cp "$src"/src/*.h "$src"/src/*.hpp "$here/x86-simd-sort/src/"
echo "$version" > "$here/NUMPY_VERSION"
echo "vendored x86-simd-sort from numpy ${version}: update the checksum in $here/README.md"
