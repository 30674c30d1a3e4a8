#!/bin/bash
# Issue 54's wrong-closure benchmark: every dataset x fraction x kind through `factord solve
# --outliers auto` (opt-in since the merge), scored against the clean optimum; with GTSAM=1 also
# GTSAM's GncLMOptimizer
# on the same files (slow: about 5 minutes per M3500 case on this machine).
#
#   benches/outliers/run.sh [WORKDIR]     (FACTORD=path/to/factord, DATA=/work/shared/data)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
work=${1:-/tmp/factord-outliers}
factord=${FACTORD:-target/release/factord}
data=${DATA:-/work/shared/data}
gtsam_python=${GTSAM_PYTHON:-$HOME/.cache/factord/venvs/gtsam/bin/python}
mkdir -p "$work"
rejected_lines() {
  python3 -c "import json,sys; print(','.join(l.rsplit(':',1)[1].rstrip(')') for l in (json.load(open(sys.argv[1])).get('outliers') or {}).get('rejected_labels', [])))" "$1"
}
printf "%-22s %-9s %5s %6s %12s %9s %7s %8s\n" dataset kind pct wrong rmse_m precision recall seconds
for entry in "M3500:2d/carlone/input_M3500_g2o.g2o" "manhattan:2d/misc/manhattanOlson3500.g2o" "sphere2500:3d/sesync/sphere2500.g2o"; do
  name=${entry%%:*}; file=$data/${entry#*:}
  "$factord" solve "$file" --outliers off --quiet --out "$work/$name.clean.g2o"
  for kind in random aliasing; do
    for pct in 0 5 20 50; do
      case=$work/$name.$kind.$pct
      python3 "$here/generate.py" --input "$file" --fraction "0.$(printf %02d "$pct")" --kind "$kind" --seed 54 \
        --out "$case.g2o" --truth "$case.truth" > /dev/null
      "$factord" solve "$case.g2o" --outliers auto --quiet --out "$case.out" --summary-json "$case.json"
      score=$(python3 "$here/evaluate.py" --clean "$work/$name.clean.g2o" --solved "$case.out" --truth "$case.truth" \
        --rejected-lines "$(rejected_lines "$case.json")")
      seconds=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['solve_seconds'])" "$case.json")
      python3 -c "import json,sys; s=json.loads(sys.argv[1]); print('%-22s %-9s %5s %6d %12.3e %9.4f %7.4f %8.3f' % (sys.argv[2], sys.argv[3], sys.argv[4], s['wrong'], s['rmse_m'], s['precision'], s['recall'], float(sys.argv[5])))" \
        "$score" "$name" "$kind" "$pct" "$seconds"
      if [ "${GTSAM:-0}" = 1 ] && [ "$pct" != 0 ]; then
        g=$("$gtsam_python" "$here/../reference/gtsam_gnc.py" --file "$case.g2o" --out "$case.gtsam.out")
        lines=$(python3 -c "import json,sys; print(','.join(map(str, json.loads(sys.argv[1])['rejected_lines'])))" "$g")
        score=$(python3 "$here/evaluate.py" --clean "$work/$name.clean.g2o" --solved "$case.gtsam.out" --truth "$case.truth" --rejected-lines "$lines")
        seconds=$(python3 -c "import json,sys; print(json.loads(sys.argv[1])['seconds'])" "$g")
        python3 -c "import json,sys; s=json.loads(sys.argv[1]); print('%-22s %-9s %5s %6d %12.3e %9.4f %7.4f %8.3f' % (sys.argv[2], sys.argv[3], sys.argv[4], s['wrong'], s['rmse_m'], s['precision'], s['recall'], float(sys.argv[5])))" \
          "$score" "$name(gtsam)" "$kind" "$pct" "$seconds"
      fi
    done
  done
done
