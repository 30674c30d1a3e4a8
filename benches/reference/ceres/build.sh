#!/usr/bin/env bash
# Build the Ceres reference drivers (ceres_pose_graph.cc, ceres_bal.cc) against Debian's
# libceres-dev.
#
#   benches/reference/ceres/build.sh [--force]
#
# Output: ${FACTORD_BENCH_BIN:-$HOME/.cache/factord/bin}/ceres_pose_graph and ceres_bal
# Idempotent: recompiles only if the binary is missing or older than the source (or --force).
# Installs the apt packages if they are missing (needs root, or sudo).
# Extra compiler flags can be passed via CXXFLAGS_EXTRA (e.g. CXXFLAGS_EXTRA=-g).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bin_dir="${FACTORD_BENCH_BIN:-$HOME/.cache/factord/bin}"
force=0
[[ "${1:-}" == "--force" ]] && force=1

ensure_packages() {
  local missing=()
  for p in libceres-dev libsuitesparse-dev libeigen3-dev libgoogle-glog-dev libgflags-dev g++ pkg-config; do
    dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
  done
  if ((${#missing[@]})); then
    echo "build.sh: installing ${missing[*]}" >&2
    local sudo=""
    [[ $(id -u) -ne 0 ]] && sudo="sudo"
    $sudo apt-get update -qq || true  # stale lists are fine if the packages are already known
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >&2
  fi
}

ensured=0
for name in ceres_pose_graph ceres_bal; do
  src="$here/$name.cc"
  out="$bin_dir/$name"
  if [[ $force -eq 0 && -x "$out" && "$out" -nt "$src" && "$out" -nt "${BASH_SOURCE[0]}" ]]; then
    echo "$out"  # up to date
    continue
  fi
  if [[ $ensured -eq 0 ]]; then
    ensure_packages
    mkdir -p "$bin_dir"
    ensured=1
  fi
  # Eigen as a system include so that -Wextra does not flood us with warnings from its headers.
  eigen_inc="$(pkg-config --variable=includedir eigen3 2>/dev/null)/eigen3"
  [[ -d "$eigen_inc" ]] || eigen_inc=/usr/include/eigen3
  # Debian's libceres-dev ships CMake config only (no .pc); the flags below are what CeresTargets uses.
  # shellcheck disable=SC2086
  g++ -std=c++17 -O3 -march=native -DNDEBUG -Wall -Wextra -Wno-unused-parameter -Wno-maybe-uninitialized \
    -isystem "$eigen_inc" ${CXXFLAGS_EXTRA:-} \
    -o "$out.tmp" "$src" \
    -lceres -lglog -lgflags -lpthread
  mv -f "$out.tmp" "$out"
  echo "$out"
done
