#!/usr/bin/env python3
"""factord's sliding window against GTSAM's fixed-lag smoother on identical inputs.

    compare.py [--seconds 140] [--windows 2,5,10,15,20,30]

For each window size, and for window 10 without the IMU and without the map priors, runs
`factord fusion-eval` (which makes the inputs from EuRoC V1_01 and writes them with
--inputs-out), then `gtsam_fixed_lag.py` (IncrementalFixedLagSmoother, iSAM2) on that same file.
Prints a markdown table of evo-style APE (translation, metres; and `-r full`) of the real-time
estimate (the newest state after each keyframe) and of the lag-smoothed one (each keyframe as it
left the window: for GTSAM, at the last update it was in the smoother), and update times.
Needs `cargo build --release` and the venv ~/.cache/factord/venvs/gtsam (made by the tests).
"""
import argparse
import json
import os
import subprocess
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=140.0)
    p.add_argument("--windows", default="2,5,10,15,20,30")
    args = p.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/factord/target"))
    factord = os.path.join(target, "release", "factord")
    python = os.path.expanduser("~/.cache/factord/venvs/gtsam/bin/python")
    runs = [(int(w), []) for w in args.windows.split(",")] + [(10, ["--no-imu"]), (10, ["--no-priors"])]
    print("| window | factors | system | APE trans rmse | mean | median | max | std | APE full rmse | lag-smoothed APE trans rmse | lag-smoothed full rmse | update p50 ms | p99 ms |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for window, extra in runs:
        with tempfile.TemporaryDirectory() as tmp:
            inputs = os.path.join(tmp, "inputs.json")
            ours = json.loads(subprocess.run(
                [factord, "fusion-eval", "--window", str(window), "--seconds", str(args.seconds),
                 "--json", "--inputs-out", inputs] + extra,
                cwd=REPO, check=True, capture_output=True, text=True).stdout)
            done = subprocess.run([python, os.path.join(HERE, "gtsam_fixed_lag.py"), inputs,
                                   "--summary-only", "--compact"], capture_output=True, text=True)
            theirs = json.loads(done.stdout) if done.stdout.strip() else {"failed": done.stderr[-200:]}
        label = {(): "IMU + lidar + priors", ("--no-imu",): "lidar + priors (no IMU)",
                 ("--no-priors",): "IMU + lidar (no priors)"}[tuple(extra)]
        for name, r, times in [("factord", ours, ours.get("update_ms")), ("GTSAM iSAM2 fixed-lag", theirs, theirs.get("solve_ms"))]:
            if "ape_trans" not in r:
                print(f"| {window} | {label} | {name} | failed: {r.get('failed')} |")
                continue
            a, f = r["ape_trans"], r["ape_full"]
            failed = " (stopped early: " + str(r["failed"]) + ")" if r.get("failed") else ""
            sa, sf = r.get("ape_smoothed_trans") or {}, r.get("ape_smoothed_full") or {}
            smoothed = (f"{sa['rmse']:.4f} | {sf['rmse']:.4f}" if sa else "— | —")
            print(f"| {window} | {label} | {name}{failed} | {a['rmse']:.4f} | {a['mean']:.4f} | {a['median']:.4f} | "
                  f"{a['max']:.4f} | {a['std']:.4f} | {f['rmse']:.4f} | {smoothed} | {times['p50']:.2f} | {times['p99']:.2f} |")


if __name__ == "__main__":
    main()
