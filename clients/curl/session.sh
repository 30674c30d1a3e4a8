#!/usr/bin/env bash
# A session by hand: create it, post a batch (waiting for the solve), read the estimate and the
# statistics, then delete it.
#
#   clients/curl/session.sh [session-name]          (default: curl-demo)
#
# FACTORD_URL (default http://127.0.0.1:8080). FACTORD_KEEP=1 keeps the session at the end (to
# watch it with events.sh or read it again).
set -euo pipefail
URL="${FACTORD_URL:-http://127.0.0.1:8080}"
S="${1:-curl-demo}"

# curl that prints the body and fails on an error status ({"error": {"code", "message", ...}}).
call() { curl -sS --fail-with-body -H 'Content-Type: application/json' "$@"; echo; }

echo "== create session $S (2D pose graph, solve after every batch)"
call -X POST "$URL/v1/sessions" \
    -d '{"session": "'"$S"'", "kind": "pose_graph_2d", "auto_optimize": {"policy": "every_batch"}}'

# Four poses around a square: pose 0 has a value, 1-3 are predicted by the server from the
# odometry factors; the last factor closes the loop. information is the upper triangle of the
# 3x3 information matrix (x, y, theta), as in g2o's EDGE_SE2.
echo "== post a batch and wait until the estimate reflects it"
call -X POST "$URL/v1/sessions/$S/batches?wait=true" -d '{
  "variables": [
    {"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
    {"key": 1, "kind": "se2"},
    {"key": 2, "kind": "se2"},
    {"key": 3, "kind": "se2"}
  ],
  "factors": [
    {"type": "between_se2", "keys": [0, 1], "measurement": [1.0, 0.0, 1.5708], "information": [100, 0, 0, 100, 0, 400]},
    {"type": "between_se2", "keys": [1, 2], "measurement": [1.1, 0.0, 1.5708], "information": [100, 0, 0, 100, 0, 400]},
    {"type": "between_se2", "keys": [2, 3], "measurement": [0.9, 0.0, 1.5708], "information": [100, 0, 0, 100, 0, 400]},
    {"type": "between_se2", "keys": [3, 0], "measurement": [1.0, 0.0, 1.5708], "sigmas": [0.1, 0.1, 0.05]}
  ]
}'

echo "== estimate (all variables; ?since=N&from=K&to=K narrow it)"
call "$URL/v1/sessions/$S/estimate"

echo "== statistics"
call "$URL/v1/sessions/$S" | python3 -c '
import json, sys
s = json.load(sys.stdin)
print("sequence %d, solved %d, %d variables, %d factors, %d solves, chi2 %s" % (
    s["sequence"], s["solved_sequence"], s["num_variables"], s["num_factors"], s["solves"],
    s["chi2"]))
'

if [ "${FACTORD_KEEP:-0}" = "1" ]; then
    echo "== keeping session $S (delete: curl -X DELETE $URL/v1/sessions/$S)"
else
    echo "== delete"
    call -X DELETE "$URL/v1/sessions/$S"
fi
