#!/usr/bin/env bash
# Property-based fuzzing of factord's HTTP API against proto/v1/openapi.json with schemathesis
# (PyPI). Starts a throwaway server, runs every check, prints schemathesis' summary, then the
# server's panics (if any) and a tally of the responses. See README.md.
#   benches/schemathesis/run.sh [extra `st run` options, e.g. --max-examples 300 --seed 7]
# Environment: FACTORD_BIN (default $CARGO_TARGET_DIR or ~/.cache/factord/target, release/factord;
# not built here), FACTORD_ST_PORT (18951), FACTORD_ST_EXAMPLES (150 per operation),
# FACTORD_ST_WORKERS (1), FACTORD_ST_SEED, FACTORD_ST_OUT (report dir, default a temp dir),
# FACTORD_ST_KNOWN (hide | show the known false positives, see hooks.py),
# FACTORD_ST_VENV (~/.cache/factord/venvs/schemathesis), FACTORD_ST_VERSION (schemathesis==4.32.5).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
bin="${FACTORD_BIN:-${CARGO_TARGET_DIR:-$HOME/.cache/factord/target}/release/factord}"
port="${FACTORD_ST_PORT:-18951}"
url="http://127.0.0.1:$port"
examples="${FACTORD_ST_EXAMPLES:-150}"
workers="${FACTORD_ST_WORKERS:-1}"
venv="${FACTORD_ST_VENV:-$HOME/.cache/factord/venvs/schemathesis}"
out="${FACTORD_ST_OUT:-$(mktemp -d /tmp/factord-schemathesis.XXXXXX)}"
mkdir -p "$out"

[ -x "$bin" ] || { echo "no factord binary at $bin (build it, or set FACTORD_BIN)" >&2; exit 2; }
if [ ! -x "$venv/bin/st" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q --upgrade pip
  "$venv/bin/pip" install -q "${FACTORD_ST_VERSION:-schemathesis==4.32.5}"
fi
"$venv/bin/st" --version

state=$(mktemp -d /tmp/factord-st-state.XXXXXX)
"$bin" serve --listen "127.0.0.1:$port" --state-dir "$state" --no-zenoh --fsync never \
  >"$out/server.out" 2>"$out/server.err" &
server=$!
cleanup() { kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; rm -rf "$state"; }
trap cleanup EXIT
for _ in $(seq 100); do
  curl -fsS "$url/v1/health" >/dev/null 2>&1 && break
  kill -0 "$server" 2>/dev/null || { cat "$out/server.err" >&2; exit 2; }
  sleep 0.1
done

seed=()
[ -n "${FACTORD_ST_SEED:-}" ] && seed=(--seed "$FACTORD_ST_SEED")
# The document is given by its absolute path so its relative $refs (*.schema.json) resolve next
# to it; st runs in $out so nothing is written into the repository.
status=0
(
  cd "$out"
  export PYTHONDONTWRITEBYTECODE=1 SCHEMATHESIS_HOOKS=hooks PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}" FACTORD_URL="$url"
  export FACTORD_ST_KNOWN="${FACTORD_ST_KNOWN:-hide}"
  "$venv/bin/st" --config-file "$here/schemathesis.toml" run "$root/proto/v1/openapi.json" \
    --url "$url" \
    --checks all \
    --max-examples "$examples" \
    --workers "$workers" \
    --exclude-operation-id streamEvents \
    --exclude-operation-id sessionWebSocket \
    --request-timeout 60 \
    --continue-on-failure \
    --output-sanitize false \
    --no-color \
    --report junit,ndjson --report-dir "$out" \
    "${seed[@]}" "$@"
) || status=$?

echo
echo "== server"
if kill -0 "$server" 2>/dev/null; then echo "still running after the run"; else echo "SERVER EXITED during the run"; status=1; fi
if grep -q "panicked" "$out/server.err"; then
  echo "PANICS in the server log ($out/server.err):"; grep -n -A3 "panicked" "$out/server.err" | head -40; status=1
else
  echo "no panic in the server log"
fi
echo
echo "== responses by operation and status (error code) — $out"
"$venv/bin/python" "$here/tally.py" "$out"/ndjson-*.ndjson || true
echo "reports: $out (junit-*.xml, ndjson-*.ndjson, server.err)"
exit "$status"
