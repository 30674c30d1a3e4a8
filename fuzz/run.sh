#!/usr/bin/env bash
# Runs every fuzz target for a while and logs the outcome.
#
#   fuzz/run.sh [seconds per target]        (default 150)
#
# Environment:
#   TARGETS="g2o toro bal json"  which targets, in order
#   SANITIZER=none               none (default: fastest; the code under test is safe Rust, so
#                                panics are what we look for) or address (nightly)
#   TOOLCHAIN                    rustup toolchain (default: stable without a sanitizer, else nightly)
#   FUZZ_TARGET_DIR              build directory (default ~/.cache/factord/fuzz-target; never the
#                                main crate's ~/.cache/factord/target)
#   NICE=19                      niceness of builds and fuzzers
#
# Per target: builds (release, debug assertions + overflow checks), fuzzes the corpus in
# fuzz/corpus/<target>/ (plus the hand-written, never minimised seeds in fuzz/seeds/<target>/)
# with the dictionary fuzz/dict/<target>.dict, minimises the corpus
# (`cargo fuzz cmin`), copies any crashing input to fuzz/crashes/<target>/ and appends a line to
# fuzz/RUNS.md. The full libFuzzer log is in fuzz/logs/<target>-<stamp>.log.
# Exit status: 0 when no target crashed, 1 otherwise (2 on a build failure).
set -u -o pipefail

SECONDS_PER_TARGET=${1:-150}
TARGETS=${TARGETS:-g2o toro bal json}
SANITIZER=${SANITIZER:-none}
NICE=${NICE:-19}

FUZZ_DIR=$(cd "$(dirname "$0")" && pwd)
cd "$FUZZ_DIR"

export CARGO_TARGET_DIR=${FUZZ_TARGET_DIR:-$HOME/.cache/factord/fuzz-target}
if [ "$(realpath -m "$CARGO_TARGET_DIR")" = "$(realpath -m "$HOME/.cache/factord/target")" ]; then
    echo "refusing to build in the main crate's target directory" >&2
    exit 2
fi

# Without a sanitizer cargo-fuzz needs no unstable flag: the stable toolchain builds and runs the
# targets (checked with rustc 1.95). AddressSanitizer needs `-Zsanitizer`, hence nightly.
# TOOLCHAIN overrides (e.g. TOOLCHAIN=nightly).
if [ -z "${TOOLCHAIN:-}" ]; then
    if [ "$SANITIZER" = none ]; then TOOLCHAIN=stable; else TOOLCHAIN=nightly; fi
fi
if [ "$TOOLCHAIN" != nightly ] && [ "$SANITIZER" != none ]; then
    # Last resort: let the stable compiler accept -Z flags.
    export RUSTC_BOOTSTRAP=1
fi
CARGO=(cargo "+$TOOLCHAIN" fuzz)
FLAGS=(-O -a -s "$SANITIZER")

RUNS=$FUZZ_DIR/RUNS.md
if [ ! -f "$RUNS" ]; then
    cat >"$RUNS" <<'EOF'
# Fuzzing runs

Appended by `fuzz/run.sh`: one line per target run. Executions are libFuzzer's
`stat::number_of_executed_units`; crashes are the inputs libFuzzer saved (crash, timeout, oom),
copied to `fuzz/crashes/<target>/`. libFuzzer stops at the first crash, so a run that crashed
is shorter than its budget.

| date (UTC) | target | seconds | executions | crashes | corpus after cmin: files (bytes) | flags |
|---|---|---|---|---|---|---|
EOF
fi

mkdir -p logs
crashed=0
for target in $TARGETS; do
    echo "== $target: building" >&2
    if ! nice -n "$NICE" "${CARGO[@]}" build "${FLAGS[@]}" "$target"; then
        echo "build of $target failed" >&2
        exit 2
    fi

    corpus=corpus/$target
    artifacts=artifacts/$target
    mkdir -p "$corpus" "$artifacts"
    stamp=$(date -u +%Y%m%dT%H%M%SZ)
    log=logs/$target-$stamp.log
    marker=$(mktemp)
    seeds=()
    [ -d "seeds/$target" ] && seeds=("seeds/$target")
    dict=()
    [ -f "dict/$target.dict" ] && dict=(-dict="dict/$target.dict")

    echo "== $target: fuzzing for ${SECONDS_PER_TARGET}s (log: fuzz/$log)" >&2
    start=$(date +%s)
    # New inputs go to the first directory; the hand-written seeds are only read.
    nice -n "$NICE" "${CARGO[@]}" run "${FLAGS[@]}" "$target" "$corpus" "${seeds[@]}" -- \
        -max_total_time="$SECONDS_PER_TARGET" -print_final_stats=1 -timeout=10 \
        -rss_limit_mb=2048 -artifact_prefix="$artifacts/" "${dict[@]}" >"$log" 2>&1
    status=$?
    # libFuzzer's own count of fuzzing time ("Done N runs in S second(s)"): the wall time also
    # holds the rebuild `cargo fuzz run` does when the sources changed after the build above.
    elapsed=$(grep -oE '^Done [0-9]+ runs in [0-9]+ second' "$log" | tail -1 | grep -oE '[0-9]+ second' | grep -oE '[0-9]+')
    [ -n "$elapsed" ] || elapsed="$(($(date +%s) - start)) (wall)"

    executions=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$log" | tail -1 | grep -oE '[0-9]+$')
    if [ -z "$executions" ]; then
        # No final stats (killed by a crash): the last `#N` status line.
        executions=$(grep -oE '^#[0-9]+' "$log" | tail -1 | tr -d '#')
    fi
    new=$(find "$artifacts" -type f -newer "$marker" \( -name 'crash-*' -o -name 'timeout-*' -o -name 'oom-*' -o -name 'leak-*' \) | sort)
    rm -f "$marker"
    crashes=0
    notes=""
    if [ -n "$new" ]; then
        mkdir -p "crashes/$target"
        for f in $new; do
            cp "$f" "crashes/$target/"
            crashes=$((crashes + 1))
            notes="$notes fuzz/crashes/$target/$(basename "$f")"
        done
        crashed=1
        echo "!! $target: $crashes crashing input(s):$notes" >&2
        grep -m1 -E "panicked at|ERROR: libFuzzer|ERROR: AddressSanitizer" "$log" >&2
    elif [ "$status" -ne 0 ]; then
        notes=" exit status $status, see fuzz/$log"
        crashed=1
    fi

    echo "== $target: minimising the corpus" >&2
    # -use_counters=0: keep one input per covered edge rather than per hit-count bucket, which
    # keeps the committed corpora small (a few hundred kB) for nearly the same edge coverage.
    nice -n "$NICE" "${CARGO[@]}" cmin "${FLAGS[@]}" "$target" "$corpus" -- -timeout=10 -use_counters=0 \
        >"logs/$target-$stamp.cmin.log" 2>&1 || echo "cmin of $target failed (see fuzz/logs/$target-$stamp.cmin.log)" >&2
    files=$(find "$corpus" -type f | wc -l)
    size="$(( $(du -sb "$corpus" | cut -f1) / 1024 )) kB"

    echo "== $target: ${elapsed}s, ${executions:-?} executions, $crashes crash(es), corpus $files files ($size)" >&2
    printf '| %s | %s | %s | %s | %s%s | %s (%s) | `+%s %s` |\n' \
        "$(date -u '+%Y-%m-%d %H:%M')" "$target" "$elapsed" "${executions:-?}" "$crashes" "$notes" \
        "$files" "$size" "$TOOLCHAIN" "${FLAGS[*]}" >>"$RUNS"
done
total=$(du -sb --apparent-size corpus | cut -f1)
echo "== corpora: $((total / 1024)) kB in all" >&2
[ "$total" -gt 1000000 ] && echo "!! the corpora exceed 1 MB: consider a lower -max_len or pruning" >&2
exit "$crashed"
