#!/usr/bin/env bash
# Graphs without vertices: factord solve (default options) and GTSAM in the same run.
#   benches/edges_only/run.sh [--repeat 5]
# Prints one JSON line per graph (factord's Summary numbers and gtsam_no_vertices.py's output)
# and a table.
set -euo pipefail
cd "$(dirname "$0")/../.."
data="${FACTORD_BENCH_DATA:-$(pwd)/../shared/data}"
repeat=5
[ "${1:-}" = "--repeat" ] && repeat="$2"
# The build directory .ci/run and benches/run.sh use (a clean build in the clone takes ~30 min).
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/factord/target}"
cargo build --release --locked
benches/reference/setup.sh >/dev/null
py="${FACTORD_BENCH_VENVS:-$HOME/.cache/factord/venvs}/gtsam/bin/python"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for graph in 2d/gtsam/w20000.txt 2d/sesync/CSAIL.g2o 2d/gtsam/victoria_park.txt; do
  [ -f "$data/$graph" ] || { echo "skipped $graph: not in $data" >&2; continue; }
  /usr/bin/time -f "%M" -o "$tmp/rss" "$CARGO_TARGET_DIR/release/factord" solve "$data/$graph" --repeat "$repeat" \
    --summary-json "$tmp/summary.json" --out "$tmp/ours.g2o" --quiet
  "$py" benches/edges_only/gtsam_no_vertices.py --file "$data/$graph" --ours "$tmp/ours.g2o" >"$tmp/gtsam.json"
  python3 - "$graph" "$tmp" <<'PY'
import json, sys
graph, tmp = sys.argv[1], sys.argv[2]
s = json.load(open(f"{tmp}/summary.json"))
g = json.load(open(f"{tmp}/gtsam.json"))
rss = int(open(f"{tmp}/rss").read().split()[-1]) / 1024
row = {"graph": graph, "factord_chi2": s["final_chi2"], "factord_iterations": s["iterations"],
       "factord_seconds": s["solve_seconds"], "factord_peak_rss_mib": rss, **{"gtsam": g}}
print(json.dumps(row))
print(f"| {graph} | {s['final_chi2']:.4f} ({s['iterations']} it) | {s['solve_seconds']:.3f} s | {rss:.0f} MiB "
      f"| {g['lm']['chi2']:.2f} ({g['lm']['iterations']} it) | {g['lm']['seconds']:.2f} s "
      f"| {g['gn']['chi2']:.4g} | {g['ours_chi2_gtsam']:.4f} → {g['gn_from_ours']['chi2']:.4f} "
      f"| {s['solve_seconds'] / g['lm']['seconds']:.4f} |")
PY
done
