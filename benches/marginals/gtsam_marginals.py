"""GTSAM's Marginals on a 2D g2o pose graph at a given estimate: the reference for factord's
marginal covariances (tests/service/marginals.rs) and the timing in BENCHMARKS.md.

    python gtsam_marginals.py GRAPH.g2o ESTIMATE.g2o --keys 1227,600 [--anchor-sigma 1e-6]

GRAPH gives the factors (read by gtsam.readG2o), ESTIMATE the values to linearise at (VERTEX_SE2
lines, e.g. factord's optimised output). factord fixes the lowest key to remove the gauge; GTSAM
gets a prior on it with a tiny sigma instead.

`--factor g2o` (default) gives GTSAM the g2o/factord residual, vec(z⁻¹ xi⁻¹ xj) = (x, y, θ), as a
CustomFactor with exact Jacobians, so the two covariance computations see the same model.
`--factor gtsam` uses BetweenFactorPose2, whose residual is Logmap(z⁻¹ xi⁻¹ xj): a different
model (0.3 mm apart in residual on intel's optimum), to show what that difference alone does. Covariances are printed in GTSAM's tangent space
(body-frame x, y, then theta) as JSON, with the time to build the factorisation and per query.
"""
import argparse
import json
import time

import gtsam
import numpy as np


def read_estimate(path):
    values = gtsam.Values()
    with open(path) as f:
        for line in f:
            tok = line.split()
            if tok and tok[0] == "VERTEX_SE2":
                values.insert(int(tok[1]), gtsam.Pose2(float(tok[2]), float(tok[3]), float(tok[4])))
    return values


def g2o_between(factor):
    """BetweenFactorPose2 `factor` with g2o's residual; Jacobians in GTSAM's body-frame tangent."""
    z_inv = factor.measured().inverse()
    i, j = factor.keys()
    J = np.array([[0.0, -1.0], [1.0, 0.0]])

    def error(_, values, H):
        m = values.atPose2(i).inverse().compose(values.atPose2(j))
        r = z_inv.compose(m)
        if H is not None:
            ra = z_inv.rotation().matrix()
            rr = r.rotation().matrix()
            t_m = np.array([m.x(), m.y()])
            hi = np.zeros((3, 3))
            hi[:2, :2] = -ra
            hi[:2, 2] = -(ra @ J @ t_m)
            hi[2, 2] = -1.0
            hj = np.eye(3)
            hj[:2, :2] = rr
            H[0] = hi
            H[1] = hj
        return np.array([r.x(), r.y(), r.theta()])

    return gtsam.CustomFactor(factor.noiseModel(), [i, j], error)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("graph")
    ap.add_argument("estimate")
    ap.add_argument("--keys", required=True)
    ap.add_argument("--anchor-sigma", type=float, default=1e-6)
    ap.add_argument("--factor", choices=["g2o", "gtsam"], default="g2o")
    ap.add_argument("--repeat", type=int, default=1, help="time this many Marginals builds")
    args = ap.parse_args()
    graph, _ = gtsam.readG2o(args.graph, False)
    if args.factor == "g2o":
        read = graph
        graph = gtsam.NonlinearFactorGraph()
        for n in range(read.size()):
            graph.add(g2o_between(read.at(n)))
    values = read_estimate(args.estimate)
    anchor = min(values.keys())
    graph.add(gtsam.PriorFactorPose2(anchor, values.atPose2(anchor),
                                     gtsam.noiseModel.Isotropic.Sigma(3, args.anchor_sigma)))
    keys = [int(k) for k in args.keys.split(",")]
    build = []
    for _ in range(max(1, args.repeat)):
        start = time.perf_counter()
        marginals = gtsam.Marginals(graph, values)
        build.append(time.perf_counter() - start)
    out = {"anchor": anchor, "build_seconds": build, "covariances": {}, "query_seconds": {}}
    for key in keys:
        start = time.perf_counter()
        cov = marginals.marginalCovariance(key)
        out["query_seconds"][str(key)] = time.perf_counter() - start
        out["covariances"][str(key)] = np.asarray(cov).tolist()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
