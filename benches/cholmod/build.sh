#!/usr/bin/env bash
# Build the CHOLMOD numeric-factorisation benchmark (cholmod_bench.c) against Debian's
# libsuitesparse-dev.
#
#   benches/cholmod/build.sh [--force]
#
# Output: ${FACTORD_BENCH_BIN:-$HOME/.cache/factord/bin}/cholmod_bench
# Idempotent: recompiles only if the binary is missing or older than the source (or --force).
# Installs libsuitesparse-dev if missing (needs root, or sudo).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
src="$here/cholmod_bench.c"
bin_dir="${FACTORD_BENCH_BIN:-$HOME/.cache/factord/bin}"
out="$bin_dir/cholmod_bench"
force=0
[[ "${1:-}" == "--force" ]] && force=1

if [[ $force -eq 0 && -x "$out" && "$out" -nt "$src" && "$out" -nt "${BASH_SOURCE[0]}" ]]; then
  echo "$out"  # up to date
  exit 0
fi

missing=()
for p in libsuitesparse-dev gcc; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "build.sh: installing ${missing[*]}" >&2
  sudo=""
  [[ $(id -u) -ne 0 ]] && sudo="sudo"
  $sudo apt-get update -qq || true
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >&2
fi

mkdir -p "$bin_dir"
gcc -std=c11 -O3 -march=native -Wall -Wextra -I/usr/include/suitesparse \
  -o "$out.tmp" "$src" \
  -lcholmod -lamd -lcolamd -lcamd -lccolamd -lsuitesparseconfig -lm
mv -f "$out.tmp" "$out"
echo "$out"
