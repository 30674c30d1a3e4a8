#!/usr/bin/env python3
"""factord in process, written as a GTSAM script (`import factord as gtsam`):

1. GTSAM's Pose2SLAMExample: five poses, a loop closure, Gauss-Newton, marginal covariances;
2. a g2o file through readG2o, Levenberg-Marquardt, numpy out, writeG2o;
3. the same file streamed pose by pose through ISAM2.

    python pose_graph.py [file.g2o] [out.g2o]
    (default file: ../shared/data/2d/carlone/input_M3500_g2o.g2o next to the checkout)
"""

import math
import os
import sys
import time

import numpy as np

import factord as gtsam
from factord.symbol_shorthand import X

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT = os.path.join(HERE, "../../../../../shared/data/2d/carlone/input_M3500_g2o.g2o")


def pose2slam():
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.3, 0.3, 0.1))
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.2, 0.2, 0.1))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(1), gtsam.Pose2(0, 0, 0), prior_noise))
    graph.add(gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(2), X(3), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(3), X(4), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(4), X(5), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(5), X(2), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))  # loop
    initial = gtsam.Values()
    for key, pose in zip(range(1, 6), [(0.5, 0.0, 0.2), (2.3, 0.1, -0.2), (4.1, 0.1, math.pi / 2),
                                       (4.0, 2.0, math.pi), (2.1, 2.1, -math.pi / 2)]):
        initial.insert(X(key), gtsam.Pose2(*pose))
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-5)
    result = gtsam.GaussNewtonOptimizer(graph, initial, params).optimize()
    print(f"Pose2SLAMExample: error {graph.error(initial):.3f} -> {graph.error(result):.3e}")
    marginals = gtsam.Marginals(graph, result)
    for i in range(1, 6):
        print(f"  {gtsam.keyName(X(i))} {result.atPose2(X(i))}")
        cov = np.array2string(marginals.marginalCovariance(X(i)), precision=4)
        print("    covariance", cov.replace("\n", "\n               "))


def batch(path, out):
    graph, initial = gtsam.readG2o(path, False)
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-6)
    start = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    seconds = time.perf_counter() - start
    poses = gtsam.utilities.extractPose2(result)  # (N, 3) numpy: x, y, θ
    print(f"{os.path.basename(path)}: {initial.size()} poses, {graph.size()} factors, error "
          f"{graph.error(initial):.1f} -> {graph.error(result):.6f} in {optimizer.iterations()} "
          f"iterations, {seconds * 1e3:.1f} ms; poses array {poses.shape}")
    if out:
        gtsam.writeG2o(graph, result, out)
        print(f"  written to {out}")
    return graph, initial, result


def stream(graph, initial, batch_result):
    by_step = {}
    for i in range(graph.size()):
        f = graph.at(i)
        if len(f.keys()) == 2:
            by_step.setdefault(max(f.keys()), []).append(f)
    isam = gtsam.ISAM2()
    estimate = None
    start = time.perf_counter()
    for k in sorted(initial.keys()):
        new_graph, new_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if estimate is None:
            new_graph.add(gtsam.PriorFactorPose2(k, initial.atPose2(k), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
            guess = initial.atPose2(k)
        else:
            odometry = [f for f in by_step.get(k, []) if k - 1 in f.keys()]
            guess = estimate.atPose2(k - 1).compose(odometry[0].measured()) if odometry else initial.atPose2(k)
        new_values.insert(k, guess)
        for f in by_step.get(k, []):
            new_graph.add(f)
        isam.update(new_graph, new_values)
        estimate = isam.calculateEstimate()
    seconds = time.perf_counter() - start
    ours, best = gtsam.utilities.extractPose2(estimate), gtsam.utilities.extractPose2(batch_result)
    gap = np.abs(ours[:, :2] - best[:, :2]).max()
    print(f"ISAM2 stream: {initial.size()} updates in {seconds:.2f} s, error "
          f"{isam.getFactorsUnsafe().error(estimate):.6f}, largest distance to the batch optimum {gap:.2e} m")


if __name__ == "__main__":
    pose2slam()
    path = sys.argv[1] if len(sys.argv) > 1 else DEFAULT
    graph, initial, result = batch(path, sys.argv[2] if len(sys.argv) > 2 else None)
    stream(graph, initial, result)
