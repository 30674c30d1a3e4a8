#!/usr/bin/env python3
"""factord's incremental session against GTSAM iSAM2, streamed the same way, interleaved.

    compare.py <g2o file> [--rounds 3] [--json out.json]

Each round runs GTSAM iSAM2 (benches/incremental/isam2_stream.py with the gtsam venv) and then
factord's `incremental_stream` bench binary on the same file, so both see the same machine state
(this VM's speed drifts by tens of percent between minutes). Prints a markdown table of the
medians over rounds and the factord/iSAM2 ratios. Build first:
`cargo bench --bench incremental_stream --no-run` (the binary is found in the target dir).
"""
import argparse
import glob
import json
import os
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def factord_binary() -> str:
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/factord/target"))
    candidates = [p for p in glob.glob(os.path.join(target, "release/deps/incremental_stream-*"))
                  if os.access(p, os.X_OK) and not p.endswith(".d")]
    if not candidates:
        sys.exit("no incremental_stream binary: run `cargo bench --bench incremental_stream --no-run`")
    return max(candidates, key=os.path.getmtime)


def run_json(cmd):
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out[out.index("{"):])


def main():
    p = argparse.ArgumentParser()
    p.add_argument("file")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json")
    args = p.parse_args()
    gtsam_python = os.path.expanduser("~/.cache/factord/venvs/gtsam/bin/python")
    if not os.path.exists(gtsam_python):
        sys.exit(f"{gtsam_python} missing: run benches/reference/setup.sh")
    binary = factord_binary()
    rounds = []
    for r in range(args.rounds):
        isam2 = run_json([gtsam_python, os.path.join(HERE, "isam2_stream.py"), args.file])
        ours = run_json([binary, args.file])
        rounds.append({"isam2": isam2, "factord": ours})
        print(f"round {r + 1}: iSAM2 {isam2['total_seconds']:.2f} s p99 {isam2['p99_ms']:.2f} ms | "
              f"factord {ours['total_seconds']:.2f} s p99 {ours['p99_ms']:.2f} ms", file=sys.stderr)

    def med(system, key):
        return statistics.median(r[system][key] for r in rounds)

    batch = rounds[0]["factord"]["batch_chi2"]
    rows = [
        ("total time (s)", "total_seconds", "{:.2f}"),
        ("mean update (ms)", "mean_ms", "{:.3f}"),
        ("p50 update (ms)", "p50_ms", "{:.3f}"),
        ("p90 update (ms)", "p90_ms", "{:.2f}"),
        ("p99 update (ms)", "p99_ms", "{:.2f}"),
        ("max update (ms)", "max_ms", "{:.1f}"),
    ]
    lines = [f"`{os.path.basename(args.file)}`, {rounds[0]['factord']['steps']} updates, "
             f"median of {len(rounds)} interleaved rounds",
             "", "| | GTSAM iSAM2 | factord | factord / iSAM2 |", "|---|---:|---:|---:|"]
    for label, key, fmt in rows:
        a, b = med("isam2", key), med("factord", key)
        lines.append(f"| {label} | {fmt.format(a)} | {fmt.format(b)} | {b / a:.2f} |")
    isam2_chi2 = med("isam2", "final_chi2_t2v") if "final_chi2_t2v" in rounds[0]["isam2"] else med("isam2", "final_chi2")
    ours_chi2 = med("factord", "streamed_estimate_chi2")
    lines.append(f"| final chi2 (our t2v convention) | {isam2_chi2:.6f} | {ours_chi2:.6f} | |")
    lines.append(f"| above the batch optimum {batch:.6f} | {isam2_chi2 / batch - 1:.2e} | "
                 f"{ours_chi2 / batch - 1:.2e} | |")
    table = "\n".join(lines)
    print(table)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rounds": rounds, "table": table}, f, indent=1)


if __name__ == "__main__":
    main()
