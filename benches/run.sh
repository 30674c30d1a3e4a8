#!/usr/bin/env bash
# Reproduces BENCHMARKS.md: builds factord and the reference drivers, then times factord, g2o,
# GTSAM and Ceres on the same files in one run, and the numeric Cholesky against CHOLMOD.
#   benches/run.sh [--repeat N] [--rounds K] [--only intel,sphere2500]   (extra args go to run_benchmarks.py)
set -euo pipefail
cd "$(dirname "$0")/.."
data="${FACTORD_BENCH_DATA:-$(pwd)/../shared/data}"
export FACTORD_BENCH_DATA="$data"
bin="${FACTORD_BENCH_BIN:-$HOME/.cache/factord/bin}"
# The build directory .ci/run uses; run_benchmarks.py looks for factord there too.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/factord/target}"
cargo build --release --locked
benches/reference/setup.sh
benches/reference/ceres/build.sh
benches/cholmod/build.sh
python3 benches/run_benchmarks.py --data "$data" "$@"

echo
echo "numeric sparse Cholesky, same matrix (H at the optimum), median ms"
echo "| graph | n | factord (faer supernodal) | CHOLMOD supernodal | CHOLMOD simplicial | factord / best CHOLMOD |"
echo "|---|---|---|---|---|---|"
tmp=$(mktemp -d)
for spec in "intel:2d/ls_slam/intel-v.dat:2d/ls_slam/intel-e.dat" "killian:2d/ls_slam/killian-v.dat:2d/ls_slam/killian-e.dat" \
            "input_M3500_g2o:2d/carlone/input_M3500_g2o.g2o:" "sphere2500:3d/sesync/sphere2500.g2o:"; do
  IFS=: read -r name graph edges <<<"$spec"
  args=("$data/$graph"); [ -n "$edges" ] && args+=(--edges "$data/$edges")
  "$CARGO_TARGET_DIR/release/factord" bench-cholesky "${args[@]}" --json --repeat 30 --write-mtx "$tmp/$name.mtx" >"$tmp/f.json"
  "$bin/cholmod_bench" --matrix "$tmp/$name.mtx" --repeat 30 --mode supernodal --ordering amd >"$tmp/a.json"
  "$bin/cholmod_bench" --matrix "$tmp/$name.mtx" --repeat 30 --mode simplicial --ordering amd >"$tmp/b.json"
  python3 - "$name" "$tmp" <<'PY'
import json, sys
name, tmp = sys.argv[1], sys.argv[2]
f = json.load(open(f"{tmp}/f.json")); a = json.load(open(f"{tmp}/a.json")); b = json.load(open(f"{tmp}/b.json"))
ours = f["supernodal"]["numeric_seconds"]; best = min(a["numeric_seconds"], b["numeric_seconds"])
print(f"| {name} | {f['n']} | {ours*1e3:.3f} | {a['numeric_seconds']*1e3:.3f} | {b['numeric_seconds']*1e3:.3f} | {ours/best:.2f} |")
PY
done
rm -rf "$tmp"
