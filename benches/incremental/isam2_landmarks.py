#!/usr/bin/env python3
"""GTSAM iSAM2 on GTSAM's 2D landmark text (victoria_park.txt), streamed pose by pose.

    isam2_landmarks.py <file> [--json out.json] [--limit N]
                       [--relinearize-threshold 0.1] [--relinearize-skip 1]

Run with the gtsam venv's python. The file is read by GTSAM's own load2D (ODOMETRY ->
BetweenFactorPose2, LANDMARK -> BearingRangeFactor2D on Symbol('l', l), the noise factord's
reader gives them too). Step k (poses in increasing id):
  1. new factors: the odometry ending at k and every sighting from k (the first pose also gets a
     prior at the origin, sigma 1e-6);
  2. new values: pose k = estimate of pose k-1 composed with the odometry (the origin for the
     first), and each landmark first seen from k placed by that sighting;
  3. isam.update(new_factors, new_values), then isam.calculateEstimate().
The timed region of a step is all of 1-3 (as isam2_stream.py). Afterwards (not timed):
final_chi2 = 2 * error of the estimate over every streamed factor (prior excluded), and the
batch optimum: LM from the chained start and Gauss-Newton from iSAM2's estimate, the lower.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import time

import numpy as np

import gtsam


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("file")
    p.add_argument("--json")
    p.add_argument("--limit", type=int)
    p.add_argument("--relinearize-threshold", type=float, default=0.1)
    p.add_argument("--relinearize-skip", type=int, default=1)
    a = p.parse_args()
    graph, _ = gtsam.load2D(a.file)
    steps: dict[int, list] = {}
    for k in range(graph.size()):
        f = graph.at(k)
        if isinstance(f, gtsam.BearingRangeFactor2D):
            pose = f.keys()[0]
        else:
            pose = max(f.keys())
        steps.setdefault(pose, []).append(f)
    poses = sorted(steps)
    if a.limit:
        poses = poses[: a.limit]
    kept = set(poses)

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(a.relinearize_threshold)
    params.relinearizeSkip = a.relinearize_skip
    isam = gtsam.ISAM2(params)
    prior = gtsam.PriorFactorPose2(poses[0], gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6))
    streamed = gtsam.NonlinearFactorGraph()
    estimate = gtsam.Values()
    latencies = []
    for k in poses:
        t0 = time.perf_counter()
        new_factors = gtsam.NonlinearFactorGraph()
        new_values = gtsam.Values()
        if k == poses[0]:
            new_factors.add(prior)
            new_values.insert(k, gtsam.Pose2())
        odometry = [f for f in steps[k] if not isinstance(f, gtsam.BearingRangeFactor2D)]
        sightings = [f for f in steps[k] if isinstance(f, gtsam.BearingRangeFactor2D)]
        for f in odometry:
            i, j = f.keys()
            if i not in kept or j not in kept:
                continue
            if not new_values.exists(k):
                z = f.measured()
                new_values.insert(k, estimate.atPose2(i).compose(z) if j == k
                                  else estimate.atPose2(j).compose(z.inverse()))
            new_factors.add(f)
        pose_k = new_values.atPose2(k)
        for f in sightings:
            l = f.keys()[1]
            if not estimate.exists(l) and not new_values.exists(l):
                m = f.measured()
                b, r = m.bearing().theta(), m.range()
                new_values.insert(l, pose_k.transformFrom(np.array([r * np.cos(b), r * np.sin(b)])))
            new_factors.add(f)
        isam.update(new_factors, new_values)
        estimate = isam.calculateEstimate()
        latencies.append(time.perf_counter() - t0)
        for i in range(new_factors.size()):
            if not isinstance(new_factors.at(i), gtsam.PriorFactorPose2):
                streamed.add(new_factors.at(i))
    peak_kb = None
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                peak_kb = int(line.split()[1])

    with_prior = gtsam.NonlinearFactorGraph(streamed)
    with_prior.add(prior)
    gn = gtsam.GaussNewtonParams()
    gn.setRelativeErrorTol(1e-9)
    gn.setAbsoluteErrorTol(1e-9)
    polished = gtsam.GaussNewtonOptimizer(with_prior, estimate, gn).optimize()
    ms = np.array(latencies) * 1e3
    final = 2 * streamed.error(estimate)
    batch = 2 * streamed.error(polished)
    out = {
        "system": "gtsam-isam2",
        "gtsam_version": importlib.metadata.version("gtsam"),
        "dataset": os.path.splitext(os.path.basename(a.file))[0],
        "limit": a.limit,
        "steps": len(poses),
        "factors": streamed.size(),
        "total_seconds": float(ms.sum() / 1e3),
        "mean_ms": float(ms.mean()),
        "p50_ms": float(np.percentile(ms, 50)),
        "p90_ms": float(np.percentile(ms, 90)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "peak_rss_kb": peak_kb,
        "final_chi2": final,
        "batch_from_isam2_chi2": batch,
        "chi2_gap": final / batch - 1.0,
        "relinearize_threshold": a.relinearize_threshold,
        "relinearize_skip": a.relinearize_skip,
    }
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
