#!/usr/bin/env bash
# Follow a session's Server-Sent Events (acks, stats, poses, summary, errors) until Ctrl-C or
# until the session is deleted.
#
#   clients/curl/events.sh SESSION
#
# FACTORD_URL (default http://127.0.0.1:8080). The session must exist, e.g.
#   FACTORD_KEEP=1 clients/curl/session.sh demo       # creates and keeps session `demo`
#   clients/curl/events.sh demo                        # terminal A: follow it
#   curl -X POST "$FACTORD_URL/v1/sessions/demo/optimize"   # terminal B: stats, poses, summary
#   curl -X DELETE "$FACTORD_URL/v1/sessions/demo"          # ends the stream
set -euo pipefail
URL="${FACTORD_URL:-http://127.0.0.1:8080}"
S="${1:?usage: events.sh SESSION}"
# -N: no buffering, print every event as it arrives.
exec curl -sS -N --fail-with-body -H 'Accept: text/event-stream' "$URL/v1/sessions/$S/events"
