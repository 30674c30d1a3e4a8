#!/usr/bin/env python3
"""GTSAM on a 2D graph file without vertices, and a check of factord's optimum in GTSAM's terms.

    python gtsam_no_vertices.py --file w20000.txt [--ours factord_result.g2o] [--max-iterations 100]

Also for landmark graphs (victoria_park.txt: load2D turns each LANDMARK into a
BearingRangeFactor2D on Symbol('l', l), the key factord uses too).

Run with the gtsam venv's python (benches/reference/setup.sh). The graph is read by GTSAM's own
`readG2o` for `.g2o` files (information), else `load2D` (NoiseFormatAUTO: w20000's `3.16228 0 0 3.16228 0 5` is a covariance xx xy xθ yy yθ θθ),
so this is GTSAM as its users run it. Start: chained odometry (pose 0 at the origin; each edge
whose first pose is placed and second is not places the second), prior σ 1e-6 on pose 0 (not
counted in χ²); landmarks start from their first sighting. χ² = 2 · graph.error.

Prints one JSON object:
- `lm`: LevenbergMarquardt from the chained start (GTSAM's default parameters, relative and
  absolute tolerance 1e-6 / 1e-9, `--max-iterations`): χ², iterations, seconds.
- `gn`: Gauss-Newton from the same start.
- with `--ours` (factord's `solve --out` file): `ours_chi2_gtsam`, factord's poses scored by
  GTSAM's error (its Pose2 Local is Logmap, factord's is t2v: the two differ at third order), and
  `gn_from_ours`: GTSAM's Gauss-Newton started there (if factord's poses are a minimum of
  GTSAM's cost too, it stays: χ² changes in the digits the error conventions differ in).
"""

from __future__ import annotations

import argparse
import json
import time

import gtsam
import numpy as np


def chained(graph: gtsam.NonlinearFactorGraph) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2())
    progress = True
    while progress:
        progress = False
        for k in range(graph.size()):
            f = graph.at(k)
            if isinstance(f, gtsam.BearingRangeFactor2D):
                i, l = f.keys()
                if values.exists(i) and not values.exists(l):
                    m = f.measured()
                    b, r = m.bearing().theta(), m.range()
                    seen = np.array([r * np.cos(b), r * np.sin(b)])
                    values.insert(l, values.atPose2(i).transformFrom(seen))
                    progress = True
                continue
            if not isinstance(f, gtsam.BetweenFactorPose2):
                continue
            i, j = f.keys()
            if values.exists(i) and not values.exists(j):
                values.insert(j, values.atPose2(i).compose(f.measured()))
                progress = True
            elif values.exists(j) and not values.exists(i):
                values.insert(i, values.atPose2(j).compose(f.measured().inverse()))
                progress = True
    return values


def solve(kind: str, graph, start, max_iterations: int):
    params = gtsam.GaussNewtonParams() if kind == "gn" else gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    t0 = time.perf_counter()
    if kind == "gn":
        optimizer = gtsam.GaussNewtonOptimizer(graph, start, params)
    else:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
    result = optimizer.optimize()
    seconds = time.perf_counter() - t0
    return result, {"iterations": optimizer.iterations(), "seconds": seconds}


def read_g2o_poses(path: str) -> gtsam.Values:
    values = gtsam.Values()
    with open(path) as f:
        for line in f:
            t = line.split()
            if t and t[0] == "VERTEX_SE2":
                values.insert(int(t[1]), gtsam.Pose2(float(t[2]), float(t[3]), float(t[4])))
            elif t and t[0] == "VERTEX_XY":
                values.insert(int(t[1]), np.array([float(t[2]), float(t[3])]))
    return values


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--file", required=True)
    p.add_argument("--ours")
    p.add_argument("--max-iterations", type=int, default=100)
    a = p.parse_args()
    if a.file.endswith(".g2o"):
        graph, _ = gtsam.readG2o(a.file, False)  # g2o: the six numbers are information
    else:
        graph, _ = gtsam.load2D(a.file)
    with_prior = gtsam.NonlinearFactorGraph(graph)
    with_prior.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    start = chained(graph)
    out = {"file": a.file, "factors": graph.size(), "variables": start.size(),
           "start_chi2": 2 * graph.error(start)}
    for kind in ("lm", "gn"):
        result, info = solve(kind, with_prior, start, a.max_iterations)
        out[kind] = {"chi2": 2 * graph.error(result), **info}
    if a.ours:
        ours = read_g2o_poses(a.ours)
        out["ours_chi2_gtsam"] = 2 * graph.error(ours)
        # Anchor GTSAM's gauge where factord's pose 0 is.
        anchored = gtsam.NonlinearFactorGraph(graph)
        anchored.add(gtsam.PriorFactorPose2(0, ours.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        result, info = solve("gn", anchored, ours, a.max_iterations)
        out["gn_from_ours"] = {"chi2": 2 * graph.error(result), **info}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
