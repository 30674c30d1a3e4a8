#!/usr/bin/env python3
"""Marginal covariances of a sliding window's keyframes: factord's service against GTSAM's
fixed-lag smoother (IncrementalFixedLagSmoother, iSAM2) on identical inputs.

    python3 benches/fusion/marginals_compare.py [--seconds 140] [--window 10] [--factord BIN]

1. Starts `factord serve` (journal on, a temporary state directory) and streams the experiment
   to it over zenoh as a robot would (`factord fusion-eval --zenoh … --keep-session`), which also
   writes the inputs file.
2. Reads the marginals of the keyframes left in the window with `GET /v1/sessions/{s}/marginals`
   (15 × 15 per keyframe, our tangent order: position (world), rotation (body), velocity,
   accelerometer bias, gyroscope bias).
3. Runs `gtsam_fixed_lag.py --marginals-out` on the same inputs file (GTSAM's own tangent orders).
4. Brings GTSAM's pose block to ours: its Pose3 tangent is [δθ (body), δt (body)] with
   t ⊕ δt = t + R δt, ours [δp (world), δθ (body)]; so δp = R δt and Σ_ours = J Σ_gtsam Jᵀ with
   J = [[0, R], [I, 0]]. Velocity (world) and biases ([acc, gyro]) are the same coordinates.
5. Prints, per block, the largest relative difference of the standard deviations (√diag) and the
   relative Frobenius difference ‖Σ_ours − Σ_gtsam‖ / ‖Σ_gtsam‖, per keyframe and over all.

The two systems linearise at their own estimates (which differ by ~0.1 mm), and GTSAM's iSAM2
relinearises only variables that moved beyond its threshold, so the covariances agree to the
extent that their linearisation points and marginalisation priors do.
"""
import argparse
import json
import os
import pathlib
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parent.parent


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def default_factord():
    target = os.environ.get("CARGO_TARGET_DIR", str(pathlib.Path.home() / ".cache/factord/target"))
    return str(pathlib.Path(target) / "release" / "factord")


def gtsam_python():
    venv = pathlib.Path.home() / ".cache/factord/venvs/gtsam/bin/python"
    return str(venv) if venv.exists() else sys.executable


def blocks(cov, use_imu):
    cov = np.asarray(cov)
    out = {"pose": cov[0:6, 0:6]}
    if use_imu:
        out["velocity"] = cov[6:9, 6:9]
        out["bias"] = cov[9:15, 9:15]
    return out


def gtsam_in_our_order(entry):
    r = np.asarray(entry["rotation"])
    j = np.zeros((6, 6))
    j[0:3, 3:6] = r           # δp (world) = R δt (body)
    j[3:6, 0:3] = np.eye(3)   # δθ (body) is the same
    out = {"pose": j @ np.asarray(entry["pose"]) @ j.T}
    if "velocity" in entry:
        out["velocity"] = np.asarray(entry["velocity"])
        out["bias"] = np.asarray(entry["bias"])
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=140.0)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--factord", default=default_factord())
    ap.add_argument("--data", default=str(REPO.parent / "shared/data/imu/euroc_V1_01_easy"),
                    help="EuRoC directory (fusion-eval --data)")
    ap.add_argument("--json", action="store_true", help="print the comparison as JSON")
    args = ap.parse_args()

    work = pathlib.Path(tempfile.mkdtemp(prefix="factord-marginals-"))
    http, zenoh = free_port(), f"tcp/127.0.0.1:{free_port()}"
    server = subprocess.Popen(
        [args.factord, "serve", "--listen", f"127.0.0.1:{http}", "--zenoh-listen", zenoh,
         "--zenoh-multicast", "off", "--state-dir", str(work / "state")],
        stdout=subprocess.DEVNULL, stderr=open(work / "serve.log", "w"))
    try:
        deadline = time.time() + 30
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{http}/v1/health", timeout=1)
                break
            except OSError:
                if time.time() > deadline or server.poll() is not None:
                    sys.exit(f"factord did not start; see {work / 'serve.log'}")
                time.sleep(0.1)
        inputs = work / "inputs.json"
        subprocess.run(
            [args.factord, "fusion-eval", "--zenoh", zenoh, "--session", "window", "--keep-session",
             "--data", args.data,
             "--window", str(args.window), "--seconds", str(args.seconds), "--inputs-out", str(inputs),
             "--json"],
            check=True, stdout=subprocess.DEVNULL, cwd=REPO)
        gtsam_out = work / "gtsam-marginals.json"
        subprocess.run(
            [gtsam_python(), str(HERE / "gtsam_fixed_lag.py"), str(inputs), "--summary-only",
             "--marginals-out", str(gtsam_out)],
            check=True, stdout=subprocess.DEVNULL)
        theirs = json.loads(gtsam_out.read_text())
        keys = ",".join(str(e["key"]) for e in theirs)
        with urllib.request.urlopen(
                f"http://127.0.0.1:{http}/v1/sessions/window/marginals?keys={keys}", timeout=30) as r:
            ours = {v["key"]: v for v in json.load(r)["variables"]}
    finally:
        server.terminate()
        server.wait(timeout=10)

    use_imu = "velocity" in theirs[0]
    rows, worst = [], {}
    for entry in theirs:
        a = blocks(ours[entry["key"]]["covariance"], use_imu)
        b = gtsam_in_our_order(entry)
        row = {"key": entry["key"]}
        for name in a:
            sigma_a, sigma_b = np.sqrt(np.diag(a[name])), np.sqrt(np.diag(b[name]))
            sigma = float(np.max(np.abs(sigma_a - sigma_b) / sigma_b))
            frobenius = float(np.linalg.norm(a[name] - b[name]) / np.linalg.norm(b[name]))
            row[name] = {"sigma_rel_max": sigma, "frobenius_rel": frobenius,
                         "sigmas_factord": sigma_a.tolist(), "sigmas_gtsam": sigma_b.tolist()}
            w = worst.setdefault(name, {"sigma_rel_max": 0.0, "frobenius_rel": 0.0})
            w["sigma_rel_max"] = max(w["sigma_rel_max"], sigma)
            w["frobenius_rel"] = max(w["frobenius_rel"], frobenius)
        rows.append(row)
    result = {"seconds": args.seconds, "window": args.window, "keyframes": len(rows),
              "worst": worst, "per_keyframe": rows}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"{len(rows)} keyframes in the window after {args.seconds} s (window {args.window})")
    print("| keyframe | block | max rel. diff of σ | rel. Frobenius diff | σ factord (first 3) | σ GTSAM (first 3) |")
    print("|---|---|---:|---:|---|---|")
    for row in rows:
        for name in ("pose", "velocity", "bias"):
            if name in row:
                c = row[name]
                fmt = lambda v: " ".join(f"{x:.3e}" for x in v[:3])
                print(f"| {row['key']} | {name} | {c['sigma_rel_max']:.2e} | {c['frobenius_rel']:.2e} | "
                      f"{fmt(c['sigmas_factord'])} | {fmt(c['sigmas_gtsam'])} |")
    print("worst:", json.dumps(worst))


if __name__ == "__main__":
    main()
