#!/usr/bin/env python3
"""Stand-in for `factord fusion-eval --inputs-out FILE`: builds a fusion inputs JSON file from a
EuRoC sequence, with numpy only, following src/fusion/experiment.rs::generate step by step
(same keyframe selection, IMU range, noise model and draw order; the random numbers themselves
differ, since this uses numpy's PCG64 and not our Rust Rng).

    python3 make_inputs.py --seconds 30 --out /tmp/inputs.json [--no-imu] [--seed 2024]

* Time origin: floor(first IMU stamp / 1e9) s; IMU t = (ns - origin*1e9) / 1e9, formed in integer ns first;
  ground truth t = float(t) - origin (as io::euroc does).
* Keyframes: every `--stride` (2) ground-truth line (20 Hz -> 10 Hz) from line `--first-truth` (20;
  that line is keyframe 0 = "initial"), while t <= t0 + seconds.
* Relative poses between consecutive keyframes from the ground truth: position in the `from`
  frame + N(0, sp^2 I), rotation R_from^T R_to Exp(n), n ~ N(0, sr^2 I)  (sp 0.02 m, sr 0.005 rad).
* Pose priors on every `--prior-every` (10)th keyframe: p + N(0, sp^2 I), R Exp(n)  (0.1 m, 0.02 rad).
* Initial velocity: forward difference of the ground truth (line first+1 minus line first).
* IMU samples with t0 < t <= t_last_keyframe; output rows are [t, ax, ay, az, gx, gy, gz]
  (the CSV has the gyro first).
"""
import argparse
import json
import math
import os
import sys

import numpy as np

DEFAULT_DATA = "/work/shared/data/imu/euroc_V1_01_easy"

# EuRoC ADIS16448 (imu0_sensor.yaml), and GTSAM's example integration sigma (= ImuNoise::EUROC).
EUROC_NOISE = {
    "accel_noise_density": 2.0e-3,
    "gyro_noise_density": 1.6968e-4,
    "accel_random_walk": 3.0e-3,
    "gyro_random_walk": 1.9393e-5,
    "integration_sigma": 1e-4,
}


def skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w):
    w = np.asarray(w, float)
    t2 = float(w @ w)
    W = skew(w)
    if t2 < 1e-12:
        return np.eye(3) + W + 0.5 * W @ W
    t = math.sqrt(t2)
    return np.eye(3) + math.sin(t) / t * W + (1.0 - math.cos(t)) / t2 * W @ W


def quat_xyzw_to_matrix(q):
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat_xyzw(R):
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd), with w >= 0."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return [float(v) for v in q]


def load_euroc(data_dir, truth_name):
    imu_path = os.path.join(data_dir, "imu0.csv")
    origin = None
    imu = []
    with open(imu_path) as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            fields = line.strip().split(",")
            ns = int(fields[0])
            if origin is None:
                origin = ns // 1_000_000_000  # floor (stamps are positive)
            v = [float(x) for x in fields[1:7]]
            t = (ns - origin * 1_000_000_000) / 1e9  # exact integer difference, one division
            imu.append((t, v[3], v[4], v[5], v[0], v[1], v[2]))  # accel first
    if origin is None:
        sys.exit(f"{imu_path}: no IMU samples")
    truth = []
    with open(os.path.join(data_dir, truth_name)) as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            v = [float(x) for x in line.split()]
            truth.append((v[0] - origin, np.array(v[1:4]), quat_xyzw_to_matrix(v[4:8])))
    return origin, imu, truth


def pose_json(p, R):
    return {"position": [float(x) for x in p], "rotation_xyzw": matrix_to_quat_xyzw(R)}


def generate(args):
    origin, imu, truth = load_euroc(args.data, args.truth)
    if len(truth) < args.first_truth + 2 * args.stride:
        sys.exit("the ground truth is too short")
    rng = np.random.default_rng(args.seed)
    t0, p0, R0 = truth[args.first_truth]
    t1, p1, _ = truth[args.first_truth + 1]
    velocity = (p1 - p0) / (t1 - t0)
    keyframes, relative, priors = [], [], []
    prev_key, (pt, pp, pR) = 0, truth[args.first_truth]
    index, key = args.first_truth + args.stride, 1
    while index < len(truth) and truth[index][0] <= t0 + args.seconds:
        t, p, R = truth[index]
        keyframes.append({"key": key, "t": t, "truth": pose_json(p, R)})
        if not args.no_relative:
            dp = pR.T @ (p - pp) + args.rel_sigma_position * rng.standard_normal(3)
            dR = pR.T @ R @ so3_exp(args.rel_sigma_rotation * rng.standard_normal(3))
            rel = pose_json(dp, dR)
            relative.append({"from": prev_key, "to": key, **rel,
                             "sigma_position": args.rel_sigma_position,
                             "sigma_rotation": args.rel_sigma_rotation})
        if args.prior_every > 0 and key % args.prior_every == 0:
            pn = p + args.prior_sigma_position * rng.standard_normal(3)
            Rn = R @ so3_exp(args.prior_sigma_rotation * rng.standard_normal(3))
            priors.append({"key": key, **pose_json(pn, Rn),
                           "sigma_position": args.prior_sigma_position,
                           "sigma_rotation": args.prior_sigma_rotation})
        prev_key, (pt, pp, pR) = key, (t, p, R)
        key += 1
        index += args.stride
    end = keyframes[-1]["t"] if keyframes else t0
    samples = [list(s) for s in imu if t0 < s[0] <= end]
    keyframe_hz = 1.0 / (truth[args.first_truth + args.stride][0] - t0)
    initial_pose = pose_json(p0, R0)
    return {
        "generation": {
            "tool": "benches/fusion/make_inputs.py (numpy stand-in for factord fusion-eval --inputs-out)",
            "data": os.path.abspath(args.data), "truth": args.truth,
            "seconds": args.seconds, "truth_stride": args.stride, "first_truth": args.first_truth,
            "prior_every": args.prior_every,
            "relative_sigma_position": args.rel_sigma_position,
            "relative_sigma_rotation": args.rel_sigma_rotation,
            "prior_sigma_position": args.prior_sigma_position,
            "prior_sigma_rotation": args.prior_sigma_rotation,
            "use_relative": not args.no_relative, "use_imu": not args.no_imu,
            "window": args.window, "seed": args.seed, "rng": "numpy PCG64 standard_normal",
        },
        "origin": origin,
        "gravity": 9.81,
        "imu_noise": dict(EUROC_NOISE),
        "window": args.window,
        "keyframe_hz": keyframe_hz,
        "use_imu": not args.no_imu,
        "initial": {
            "key": 0, "t": t0, **initial_pose,
            "velocity": [float(x) for x in velocity],
            "accel_bias": [0.0, 0.0, 0.0], "gyro_bias": [0.0, 0.0, 0.0],
            "sigmas": {"position": 0.01, "rotation": 0.01, "velocity": 0.1,
                       "accel_bias": 0.1, "gyro_bias": 0.01},
        },
        "initial_truth": initial_pose,
        "imu": samples,
        "keyframes": keyframes,
        "relative_poses": relative,
        "pose_priors": priors,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=DEFAULT_DATA)
    ap.add_argument("--truth", default="groundtruth_20hz_tum.txt")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--stride", type=int, default=2, help="keyframe every N ground-truth lines")
    ap.add_argument("--first-truth", type=int, default=20)
    ap.add_argument("--prior-every", type=int, default=10, help="0: no pose priors")
    ap.add_argument("--rel-sigma-position", type=float, default=0.02)
    ap.add_argument("--rel-sigma-rotation", type=float, default=0.005)
    ap.add_argument("--prior-sigma-position", type=float, default=0.1)
    ap.add_argument("--prior-sigma-rotation", type=float, default=0.02)
    ap.add_argument("--no-imu", action="store_true", help='write "use_imu": false')
    ap.add_argument("--no-relative", action="store_true")
    ap.add_argument("--out", "-o", default="-", help="output file (default stdout)")
    args = ap.parse_args()
    inputs = generate(args)
    text = json.dumps(inputs)
    if args.out == "-":
        print(text)
    else:
        with open(args.out, "w") as f:
            f.write(text)
        print(f"wrote {args.out}: {len(inputs['keyframes'])} keyframes, {len(inputs['imu'])} IMU samples, "
              f"{len(inputs['relative_poses'])} relative poses, {len(inputs['pose_priors'])} priors",
              file=sys.stderr)


if __name__ == "__main__":
    main()
