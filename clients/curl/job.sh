#!/usr/bin/env bash
# Optimise a whole graph file in one request (POST /v1/jobs) and print the result's summary.
#
#   clients/curl/job.sh [graph-file]        (default: $FACTORD_DATA/2d/converted/intel_lsslam.g2o)
#
# FACTORD_URL (default http://127.0.0.1:8080), FACTORD_DATA (default ../shared/data from the
# repository root). Query parameters: FACTORD_JOB_PARAMS, e.g. "format=g2o&method=lm&max_iterations=50".
set -euo pipefail
URL="${FACTORD_URL:-http://127.0.0.1:8080}"
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
DATA="${FACTORD_DATA:-$ROOT/../shared/data}"
FILE="${1:-$DATA/2d/converted/intel_lsslam.g2o}"
PARAMS="${FACTORD_JOB_PARAMS:-}"

# --data-binary keeps the file's newlines. ?format=g2o|toro (detected from the content when
# absent); an error answer is {"error": {"code", "message", "field", "status"}}.
if ! answer=$(curl -sS --fail-with-body -X POST \
        -H 'Content-Type: text/plain' \
        --data-binary @"$FILE" \
        "$URL/v1/jobs${PARAMS:+?$PARAMS}"); then
    echo "job failed: $answer" >&2
    exit 1
fi
printf '%s' "$answer" | python3 -c '
import json, sys
answer = json.load(sys.stdin)
s = answer["summary"]
print("initial_chi2 %.6f" % s["initial_chi2"])
print("final_chi2   %.6f" % s["final_chi2"])
print("iterations   %d (%s, %s)" % (s["iterations"], s["method"], s["termination"]["reason"]))
print("solve time   %.1f ms" % (s["solve_seconds"] * 1e3))
print("poses        %d" % len(answer["estimate"]["variables"]))
'
# The optimised graph as g2o text instead of JSON:
#   curl -sS -X POST --data-binary @"$FILE" "$URL/v1/jobs?output=g2o" > optimised.g2o
