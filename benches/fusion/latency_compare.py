#!/usr/bin/env python3
"""Update latency of factord's sliding window against GTSAM's fixed-lag smoother, interleaved.

    latency_compare.py [--seconds 140] [--windows 10,20] [--repeat 3] [--baseline OLD_FACTORD]
                       [--factord FACTORD]

For each window size: makes the inputs once (`factord fusion-eval --inputs-out`), then runs
`repeat` rounds of [baseline factord (if given), factord, gtsam_fixed_lag.py] on that same file,
one after the other, so that every system sees the same machine load. Prints each round and the
median over rounds of p50 / p99 update time, APE (translation rmse) and mean Gauss-Newton steps
per keyframe. factord's update time is adding the keyframe's IMU samples, the keyframe and its
measurements, optimising and marginalising; GTSAM's is its `update()` call only (factor
construction and pre-integration excluded), so the comparison is conservative for factord.
Needs `cargo build --release` and the venv ~/.cache/factord/venvs/gtsam (made by the tests).
"""
import argparse
import json
import os
import statistics
import subprocess
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def factord_run(binary, inputs):
    r = json.loads(subprocess.run([binary, "fusion-eval", "--inputs", inputs, "--json"], cwd=REPO,
                                  check=True, capture_output=True, text=True).stdout)
    return {"p50": r["update_ms"]["p50"], "p99": r["update_ms"]["p99"],
            "ape": r["ape_trans"]["rmse"], "steps": r["iterations_mean"]}


def gtsam_run(python, inputs):
    done = subprocess.run([python, os.path.join(HERE, "gtsam_fixed_lag.py"), inputs, "--summary-only",
                           "--compact"], capture_output=True, text=True, check=True)
    r = json.loads(done.stdout)
    return {"p50": r["solve_ms"]["p50"], "p99": r["solve_ms"]["p99"], "ape": r["ape_trans"]["rmse"],
            "steps": 1.0}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=140.0)
    p.add_argument("--windows", default="10,20")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--baseline", help="another factord binary to run in the same rounds")
    p.add_argument("--factord", help="the factord binary (default: $CARGO_TARGET_DIR/release/factord)")
    args = p.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/factord/target"))
    factord = args.factord or os.path.join(target, "release", "factord")
    python = os.path.expanduser("~/.cache/factord/venvs/gtsam/bin/python")
    systems = ([("factord (baseline)", lambda i: factord_run(args.baseline, i))] if args.baseline else [])
    systems += [("factord", lambda i: factord_run(factord, i)), ("GTSAM fixed-lag", lambda i: gtsam_run(python, i))]
    rows = []
    for window in [int(w) for w in args.windows.split(",")]:
        with tempfile.TemporaryDirectory() as tmp:
            inputs = os.path.join(tmp, "inputs.json")
            subprocess.run([factord, "fusion-eval", "--window", str(window), "--seconds", str(args.seconds),
                            "--json", "--inputs-out", inputs], cwd=REPO, check=True, capture_output=True)
            runs = {name: [] for name, _ in systems}
            for round_ in range(args.repeat):
                for name, run in systems:
                    r = run(inputs)
                    runs[name].append(r)
                    print(f"# window {window} round {round_ + 1} {name}: p50 {r['p50']:.3f} ms, p99 {r['p99']:.3f} ms, "
                          f"APE {r['ape']:.6f} m, steps {r['steps']:.3f}", flush=True)
        for name, _ in systems:
            med = {k: statistics.median(r[k] for r in runs[name]) for k in ("p50", "p99", "ape", "steps")}
            rows.append((window, name, med))
    print(f"| window | system | update p50 ms | p99 ms | APE trans rmse m | GN steps / keyframe |  (median of {args.repeat} interleaved rounds)")
    print("|---|---|---:|---:|---:|---:|")
    for window, name, m in rows:
        print(f"| {window} | {name} | {m['p50']:.3f} | {m['p99']:.3f} | {m['ape']:.6f} | {m['steps']:.3f} |")


if __name__ == "__main__":
    main()
