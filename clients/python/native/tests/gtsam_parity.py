"""The same scripts run with ``import gtsam`` and with ``import factord as gtsam``; the results are
compared here. Run by the native Python environment (factord installed); GTSAM runs in its own
environment through ``--gtsam-python`` (this file again, with ``--worker``).

Scenarios: GTSAM's Pose2SLAMExample and PlanarSLAMExample as published, input_M3500_g2o through
readG2o, a small noisy Pose3 loop, position fixes written as GTSAM's ``CustomFactor`` (a Python error
function with its Jacobian in GTSAM's tangent), landmarks seen by bearing only with point
priors and betweens, and GPS fixes of a Pose3 chain (at its origin and on a lever arm). For each: the optimum, the graph error, and the marginal
covariances where the example prints them; then each library scores the other's optimum with its
own ``graph.error``.

The Pose2 and Pose3 between errors differ by definition (GTSAM: Logmap of the relative error;
factord: translation of the relative error then its angle, as g2o), so the two final errors of a
graph whose optimum leaves residuals differ by a little (M3500: 1.4e-5 relative); the optimum each
finds is the other's to second order, which the cross-scoring measures.
"""

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np


# ---------------------------------------------------------------- the scenarios (either library)


def optimize_tightly(gtsam, graph, initial, max_iterations=None):
    """Levenberg-Marquardt to tolerances 1e-12, so both libraries end at their optimum."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    if max_iterations is not None:
        params.setMaxIterations(max_iterations)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


def pose2slam(gtsam):
    X = gtsam.symbol_shorthand.X
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.3, 0.3, 0.1))
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.2, 0.2, 0.1))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(1), gtsam.Pose2(0, 0, 0), prior_noise))
    graph.add(gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(2), X(3), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(3), X(4), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(4), X(5), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(X(5), X(2), gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    initial = gtsam.Values()
    initial.insert(X(1), gtsam.Pose2(0.5, 0.0, 0.2))
    initial.insert(X(2), gtsam.Pose2(2.3, 0.1, -0.2))
    initial.insert(X(3), gtsam.Pose2(4.1, 0.1, math.pi / 2))
    initial.insert(X(4), gtsam.Pose2(4.0, 2.0, math.pi))
    initial.insert(X(5), gtsam.Pose2(2.1, 2.1, -math.pi / 2))
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-5)
    params.setMaxIterations(100)
    result = gtsam.GaussNewtonOptimizer(graph, initial, params).optimize()
    marginals = gtsam.Marginals(graph, result)
    keys = [X(i) for i in range(1, 6)]
    return graph, result, {
        "poses2": gtsam.utilities.extractPose2(result).tolist(),
        "covariances": [marginals.marginalCovariance(k).tolist() for k in keys],
    }


def planarslam(gtsam):
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.3, 0.3, 0.1]))
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2, 0.2, 0.1]))
    measurement_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.2]))
    x1, x2, x3, l1, l2 = X(1), X(2), X(3), L(4), L(5)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(x1, gtsam.Pose2(0.0, 0.0, 0.0), prior_noise))
    graph.add(gtsam.BetweenFactorPose2(x1, x2, gtsam.Pose2(2.0, 0.0, 0.0), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(x2, x3, gtsam.Pose2(2.0, 0.0, 0.0), odometry_noise))
    graph.add(gtsam.BearingRangeFactor2D(x1, l1, gtsam.Rot2.fromDegrees(45), np.sqrt(4.0 + 4.0), measurement_noise))
    graph.add(gtsam.BearingRangeFactor2D(x2, l1, gtsam.Rot2.fromDegrees(90), 2.0, measurement_noise))
    graph.add(gtsam.BearingRangeFactor2D(x3, l2, gtsam.Rot2.fromDegrees(90), 2.0, measurement_noise))
    initial = gtsam.Values()
    initial.insert(x1, gtsam.Pose2(-0.25, 0.20, 0.15))
    initial.insert(x2, gtsam.Pose2(2.30, 0.10, -0.20))
    initial.insert(x3, gtsam.Pose2(4.10, 0.10, 0.10))
    initial.insert(l1, gtsam.Point2(1.80, 2.10))
    initial.insert(l2, gtsam.Point2(4.10, 1.80))
    result = optimize_tightly(gtsam, graph, initial)
    marginals = gtsam.Marginals(graph, result)
    return graph, result, {
        "poses2": gtsam.utilities.extractPose2(result).tolist(),
        "points2": gtsam.utilities.extractPoint2(result).tolist(),
        "covariances": [marginals.marginalCovariance(k).tolist() for k in (x1, x2, x3, l1, l2)],
    }


def m3500(gtsam, data_dir):
    path = os.path.join(data_dir, "2d/carlone/input_M3500_g2o.g2o")
    graph, initial = gtsam.readG2o(path, False)
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 1e-4]))))
    result = optimize_tightly(gtsam, graph, initial, max_iterations=200)
    return graph, result, {"poses2": gtsam.utilities.extractPose2(result).tolist()}


def pose3_loop(gtsam):
    """Twelve poses on a rising circle, odometry and two loop closures with fixed pseudo-noise."""
    n = 12
    rng = np.random.RandomState(56)
    truth = [
        gtsam.Pose3(gtsam.Rot3.Ypr(2 * math.pi * i / n, 0.05 * math.sin(i), 0.0),
                    gtsam.Point3(5 * math.cos(2 * math.pi * i / n), 5 * math.sin(2 * math.pi * i / n), 0.2 * i))
        for i in range(n)
    ]
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.02, 0.02, 0.02, 0.1, 0.1, 0.1]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))

    def measured(a, b):
        wiggle = np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 0.1, 3)])
        return truth[a].between(truth[b]).compose(gtsam.Pose3.Expmap(wiggle))

    for i in range(n - 1):
        graph.add(gtsam.BetweenFactorPose3(i, i + 1, measured(i, i + 1), noise))
    graph.add(gtsam.BetweenFactorPose3(n - 1, 0, measured(n - 1, 0), noise))
    graph.add(gtsam.BetweenFactorPose3(2, 8, measured(2, 8), noise))
    initial = gtsam.Values()
    for i in range(n):
        start = np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.3, 3)])
        initial.insert(i, truth[i].compose(gtsam.Pose3.Expmap(start)))
    result = optimize_tightly(gtsam, graph, initial)
    return graph, result, {"poses3": gtsam.utilities.extractPose3(result).tolist()}


def custom_gps(gtsam):
    """GTSAM's CustomFactor as its documentation writes it: position fixes on a Pose2 chain, the
    error function giving its Jacobian in GTSAM's body-frame tangent."""
    X = gtsam.symbol_shorthand.X
    n = 20
    rng = np.random.RandomState(57)
    step = gtsam.Pose2(1.0, 0.0, 2 * math.pi / n)
    odometry = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.05]))
    fix_noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)

    def gps(measured):
        def error_func(this, values, H):
            pose = values.atPose2(this.keys()[0])
            if H is not None:
                H[0] = np.hstack([pose.rotation().matrix(), np.zeros((2, 1))])
            return pose.translation() - measured

        return error_func

    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    truth = gtsam.Pose2(0.0, 0.0, 0.0)
    for i in range(n):
        if i:
            wiggle = gtsam.Pose2(rng.normal(0, 0.1), rng.normal(0, 0.1), rng.normal(0, 0.05))
            graph.add(gtsam.BetweenFactorPose2(X(i - 1), X(i), step.compose(wiggle), odometry))
            truth = truth.compose(step)
        fix = np.array([truth.x(), truth.y()]) + rng.normal(0, 0.5, 2)
        graph.add(gtsam.CustomFactor(fix_noise, [X(i)], gps(fix)))
        initial.insert(X(i), gtsam.Pose2(truth.x() + 0.3, truth.y() - 0.2, truth.theta() + 0.1))
    result = optimize_tightly(gtsam, graph, initial)
    return graph, result, {"poses2": gtsam.utilities.extractPose2(result).tolist()}


def bearings(gtsam):
    """Landmarks seen by bearing only from noisy poses, one landmark with a position prior and a
    measured offset to the next: BearingFactor2D, PriorFactorPoint2, BetweenFactorPoint2."""
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    rng = np.random.RandomState(58)
    marks = [np.array([4.0, 3.0]), np.array([-2.0, 5.0]), np.array([1.0, -4.0])]
    pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.01]))
    bearing_noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.02)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for i in range(6):
        a = 2 * math.pi * i / 6
        pose = gtsam.Pose2(6 * math.cos(a), 6 * math.sin(a), a + math.pi / 2)
        graph.add(gtsam.PriorFactorPose2(X(i), pose, pose_noise))
        initial.insert(X(i), pose)
        for j, m in enumerate(marks):
            seen = math.atan2(m[1] - pose.y(), m[0] - pose.x()) - pose.theta() + rng.normal(0, 0.02)
            graph.add(gtsam.BearingFactor2D(X(i), L(j), gtsam.Rot2(seen), bearing_noise))
    graph.add(gtsam.PriorFactorPoint2(L(0), gtsam.Point2(4.1, 2.9), gtsam.noiseModel.Isotropic.Sigma(2, 0.2)))
    graph.add(gtsam.BetweenFactorPoint2(L(0), L(1), gtsam.Point2(-6.1, 2.05), gtsam.noiseModel.Isotropic.Sigma(2, 0.1)))
    for j, m in enumerate(marks):
        initial.insert(L(j), gtsam.Point2(m[0] + 0.7, m[1] - 0.6))
    result = optimize_tightly(gtsam, graph, initial)
    return graph, result, {
        "poses2": gtsam.utilities.extractPose2(result).tolist(),
        "points2": gtsam.utilities.extractPoint2(result).tolist(),
    }


def gps3(gtsam):
    """A Pose3 chain with noisy odometry, GPS fixes of its origin (GPSFactor) and of an antenna on
    a lever arm (GPSFactorArm)."""
    X = gtsam.symbol_shorthand.X
    rng = np.random.RandomState(59)
    step = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, 0.02, -0.01), gtsam.Point3(1.0, 0.1, 0.05))
    odometry = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05]))
    fix = gtsam.noiseModel.Isotropic.Sigma(3, 0.3)
    arm = gtsam.Point3(0.4, -0.2, 1.1)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    truth = gtsam.Pose3()
    for i in range(15):
        if i:
            wiggle = np.concatenate([rng.normal(0, 0.01, 3), rng.normal(0, 0.05, 3)])
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step.compose(gtsam.Pose3.Expmap(wiggle)), odometry))
            truth = truth.compose(step)
        if i % 2:
            antenna = truth.transformFrom(arm) + rng.normal(0, 0.3, 3)
            graph.add(gtsam.GPSFactorArm(X(i), antenna, arm, fix))
        else:
            graph.add(gtsam.GPSFactor(X(i), truth.translation() + rng.normal(0, 0.3, 3), fix))
        start = np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.3, 3)])
        initial.insert(X(i), truth.compose(gtsam.Pose3.Expmap(start)))
    result = optimize_tightly(gtsam, graph, initial)
    return graph, result, {"poses3": gtsam.utilities.extractPose3(result).tolist()}


SCENARIOS = {
    "pose2slam": lambda g, d: pose2slam(g),
    "planarslam": lambda g, d: planarslam(g),
    "m3500": m3500,
    "pose3_loop": lambda g, d: pose3_loop(g),
    "custom_gps": lambda g, d: custom_gps(g),
    "bearings": lambda g, d: bearings(g),
    "gps3": lambda g, d: gps3(g),
}


def values_from(gtsam, template, rows):
    """A Values with `template`'s keys (in key order) holding the other library's rows."""
    values = gtsam.Values()
    keys = sorted(template.keys())
    pose2 = iter(rows.get("poses2", []))
    point2 = iter(rows.get("points2", []))
    pose3 = iter(rows.get("poses3", []))
    for k in keys:
        try:
            template.atPose2(k)
            x, y, t = next(pose2)
            values.insert(k, gtsam.Pose2(x, y, t))
            continue
        except Exception:
            pass
        try:
            template.atPose3(k)
            r = next(pose3)
            values.insert(k, gtsam.Pose3(gtsam.Rot3(np.array(r[:9]).reshape(3, 3)), np.array(r[9:])))
            continue
        except Exception:
            pass
        values.insert(k, np.array(next(point2), dtype=float))
    return values


def worker(library, data_dir, other_json):
    """Runs every scenario with `library`; with `other_json`, scores the other library's optima."""
    if library == "gtsam":
        import gtsam
    else:
        import factord as gtsam
    other = json.load(open(other_json)) if other_json else {}
    out = {}
    for name, scenario in SCENARIOS.items():
        graph, result, rows = scenario(gtsam, data_dir)
        rows["error"] = graph.error(result)
        if name in other:
            rows["error_at_other"] = graph.error(values_from(gtsam, result, other[name]))
        out[name] = rows
    return out


# ---------------------------------------------------------------- the comparison (driver)


def relative(a, b):
    return abs(a - b) / max(abs(a), abs(b), 1e-300)


def angle_diff(a, b):
    return (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi


def max_pose2_diff(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return max(np.abs(a[:, :2] - b[:, :2]).max(), np.abs(angle_diff(a[:, 2], b[:, 2])).max())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", choices=["gtsam", "factord"])
    ap.add_argument("--other")
    ap.add_argument("--out")
    ap.add_argument("--gtsam-python")
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--scratch", default=".")
    args = ap.parse_args()
    if args.worker:
        json.dump(worker(args.worker, args.data_dir, args.other), open(args.out, "w"))
        return

    def run(library, other=None):
        out = os.path.join(args.scratch, f"{library}{'-scored' if other else ''}.json")
        python = args.gtsam_python if library == "gtsam" else sys.executable
        cmd = [python, __file__, "--worker", library, "--data-dir", args.data_dir, "--out", out]
        if other:
            cmd += ["--other", other]
        subprocess.run(cmd, check=True)
        return out, json.load(open(out))

    g_path, _ = run("gtsam")
    f_path, _ = run("factord")
    _, g = run("gtsam", f_path)
    _, f = run("factord", g_path)
    failures = []

    def check(ok, line):
        print(("ok   " if ok else "FAIL ") + line)
        if not ok:
            failures.append(line)

    # Pose2SLAMExample: consistent measurements, so both optima are exact; marginals in GTSAM's
    # body-frame convention.
    d = max_pose2_diff(g["pose2slam"]["poses2"], f["pose2slam"]["poses2"])
    check(d < 1e-9, f"pose2slam: poses differ by {d:.2e} (< 1e-9)")
    c = np.abs(np.array(g["pose2slam"]["covariances"]) - np.array(f["pose2slam"]["covariances"])).max()
    check(c < 1e-9, f"pose2slam: marginal covariances differ by {c:.2e} (< 1e-9)")
    # PlanarSLAMExample.
    d = max(max_pose2_diff(g["planarslam"]["poses2"], f["planarslam"]["poses2"]),
            np.abs(np.array(g["planarslam"]["points2"]) - np.array(f["planarslam"]["points2"])).max())
    check(d < 1e-9, f"planarslam: poses and landmarks differ by {d:.2e} (< 1e-9)")
    c = max(np.abs(np.array(a) - np.array(b)).max()
            for a, b in zip(g["planarslam"]["covariances"], f["planarslam"]["covariances"]))
    check(c < 1e-6, f"planarslam: marginal covariances differ by {c:.2e} (< 1e-6)")
    # (PlanarSLAMExample's optimum has zero error: compared by its optimum above.)
    for name in ("m3500", "pose3_loop", "custom_gps", "bearings", "gps3"):
        ge, fe = g[name]["error"], f[name]["error"]
        # Each library's error at the other's optimum equals its own optimum's.
        rg = relative(g[name]["error_at_other"], ge)
        rf = relative(f[name]["error_at_other"], fe)
        check(rg < 1e-6, f"{name}: GTSAM's error at factord's optimum {g[name]['error_at_other']:.10f} vs its own {ge:.10f}: {rg:.1e} relative (< 1e-6)")
        check(rf < 1e-6, f"{name}: factord's error at GTSAM's optimum {f[name]['error_at_other']:.10f} vs its own {fe:.10f}: {rf:.1e} relative (< 1e-6)")
        r = relative(ge, fe)
        check(r < 1e-4, f"{name}: final errors GTSAM {ge:.10f}, factord {fe:.10f}: {r:.1e} relative (< 1e-4: the between errors' definitions)")
    d = max_pose2_diff(g["m3500"]["poses2"], f["m3500"]["poses2"])
    check(d < 1e-3, f"m3500: poses differ by {d:.2e} (< 1e-3)")
    d = max_pose2_diff(g["custom_gps"]["poses2"], f["custom_gps"]["poses2"])
    check(d < 1e-3, f"custom_gps: poses differ by {d:.2e} (< 1e-3)")
    d = np.abs(np.array(g["bearings"]["points2"]) - np.array(f["bearings"]["points2"])).max()
    check(d < 1e-6, f"bearings: landmarks differ by {d:.2e} (< 1e-6)")
    p = np.abs(np.array(g["gps3"]["poses3"]) - np.array(f["gps3"]["poses3"])).max()
    check(p < 1e-3, f"gps3: rotation and translation entries differ by {p:.2e} (< 1e-3)")
    p = np.abs(np.array(g["pose3_loop"]["poses3"]) - np.array(f["pose3_loop"]["poses3"])).max()
    check(p < 1e-3, f"pose3_loop: rotation and translation entries differ by {p:.2e} (< 1e-3)")
    if failures:
        sys.exit(f"{len(failures)} comparison(s) failed")
    print("gtsam parity: all comparisons hold")


if __name__ == "__main__":
    main()
