#!/usr/bin/env python3
"""GTSAM reference driver for the factord benchmarks (run with the gtsam venv's python).

    python gtsam_solve.py --file PATH [--edges PATH] [--format auto|g2o|toro] [--method gn|lm]
                          [--repeat N] [--max-iterations 100]

Prints ONE JSON object on stdout (see driver_common.new_result for the fields).

Problem: parsed by posegraph_io (not gtsam.readG2o, so GTSAM and g2o get exactly the same data).
Each edge is a BetweenFactorPose2/Pose3 with noiseModel.Gaussian.Information(Omega).  Pose2's
tangent order (x, y, theta) is the file's; for Pose3 (tangent (R, t)) the file's (t, R)
information is block-swapped.  No robust kernel.  With --se3-info g2o (what run_benchmarks.py
uses) the rotation rows/columns are first scaled by 1/2 (Logmap ~ 2 qvec), so GTSAM minimises g2o's
3D cost up to O(theta^3) per edge and the optima are comparable; the default 'file' applies the
file's information to the Logmap error unchanged, as gtsam.readG2o does.
Gauge: PriorFactor on the lowest-id pose at its initial value with isotropic sigma 1e-6 (a hard
constraint is not usable with Cholesky).  The prior is excluded from the reported chi2.

Solver: GaussNewtonOptimizer (gn) or LevenbergMarquardtOptimizer (lm, GTSAM's default lambda
schedule), linear solver MULTIFRONTAL_CHOLESKY, COLAMD ordering (GTSAM defaults).
Termination (GTSAM's own checkConvergence, evaluated on its error = chi2/2):
    relativeErrorTol = 1e-6   stop when (E_prev - E)/E_prev <= 1e-6   (same threshold as g2o's gain)
    absoluteErrorTol = 1e-9   stop when E_prev - E <= 1e-9 (also catches an error *increase*)
    errorTol         = 0
    maxIterations    = --max-iterations (100)
"converged" is true only if it stopped before maxIterations on a non-increasing error
(per-iteration errors are recorded with params.iterationHook); a GN step that increases the error
stops GTSAM but is reported as not converged.

Timing: each of --repeat runs constructs the optimizer from the same untouched initial Values
(construction computes the COLAMD ordering and the initial error, so it is timed; the
construction part alone is also reported as setup_seconds_runs) and calls optimize();
time.perf_counter around both.  solve_seconds is the median over runs.  Graph building and chi2
evaluation are outside the timed region.

chi2: final_chi2 = 2 * graph.error(values) on the graph without the gauge prior, i.e. GTSAM's
own error convention: BetweenFactor uses Local(z, Xi^-1 Xj) = Logmap(Z^-1 Xi^-1 Xj) in this build
(Pose2: (V^-1 t, theta), not t2v; Pose3: (omega, V^-1 t)).  final_chi2_g2o re-evaluates the result
in g2o's convention (2D t2v, 3D [t; qvec]) with numpy, for comparisons with g2o and factord.
"""

from __future__ import annotations

import math
import sys

import numpy as np

import gtsam

import driver_common as dc
from posegraph_io import PoseGraph, chi2_g2o_convention

GAUGE_SIGMA = 1e-6
ABSOLUTE_ERROR_TOL = 1e-9
SWAP_T_R = [3, 4, 5, 0, 1, 2]  # (t, R) <-> (R, t)


def to_pose(dim: int, p):
    if dim == 2:
        return gtsam.Pose2(p[0], p[1], p[2])
    rot = gtsam.Rot3.Quaternion(p[6], p[3], p[4], p[5])  # (w, x, y, z)
    return gtsam.Pose3(rot, np.array(p[:3], dtype=float))


def from_pose(dim: int, pose):
    if dim == 2:
        return (pose.x(), pose.y(), pose.theta())
    q = pose.rotation().toQuaternion()
    t = pose.translation()
    return (t[0], t[1], t[2], q.x(), q.y(), q.z(), q.w())


def build(graph: PoseGraph, se3_info: str = "file"):
    """(graph without prior, graph with gauge prior, initial Values).

    se3_info='file' applies the file's information to GTSAM's Logmap error (what gtsam.readG2o
    does); 'g2o' scales the rotation block by 1/2 on each side (D Omega D, D = diag(1,1,1,.5,.5,.5))
    so that, since Logmap ~ 2 qvec, the cost equals g2o's [t; qvec] cost up to O(theta^3) per edge.
    """
    factors = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for vid, p in graph.vertices.items():
        initial.insert(vid, to_pose(graph.dim, p))
    for e in graph.edges:
        info = np.array(e.information, dtype=float)
        z = to_pose(graph.dim, e.measurement)
        if graph.dim == 2:
            factors.add(gtsam.BetweenFactorPose2(e.i, e.j, z, gtsam.noiseModel.Gaussian.Information(info)))
        else:
            if se3_info == "g2o":
                d = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
                info = info * np.outer(d, d)
            info = info[np.ix_(SWAP_T_R, SWAP_T_R)]
            factors.add(gtsam.BetweenFactorPose3(e.i, e.j, z, gtsam.noiseModel.Gaussian.Information(info)))
    with_prior = gtsam.NonlinearFactorGraph(factors)
    g0 = graph.first_vertex
    dof = 3 if graph.dim == 2 else 6
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(dof, GAUGE_SIGMA)
    prior_cls = gtsam.PriorFactorPose2 if graph.dim == 2 else gtsam.PriorFactorPose3
    with_prior.add(prior_cls(g0, to_pose(graph.dim, graph.vertices[g0]), prior_noise))
    return factors, with_prior, initial


def make_params(method: str, max_iterations: int, hook):
    params = gtsam.GaussNewtonParams() if method == "gn" else gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(dc.RELATIVE_DECREASE_TOL)
    params.setAbsoluteErrorTol(ABSOLUTE_ERROR_TOL)
    params.setErrorTol(0.0)
    params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
    params.iterationHook = hook
    return params


def main() -> int:
    args = dc.parse_args("gtsam", extra=lambda p: p.add_argument(
        "--se3-info", choices=["file", "g2o"], default="file",
        help="3D only: 'file' = file information on GTSAM's Logmap error (as gtsam.readG2o); "
             "'g2o' = D*Omega*D, D = diag(1,1,1,1/2,1/2,1/2), so the cost matches g2o's [t; qvec] "
             "convention up to O(theta^3) (used by run_benchmarks.py)"))
    result = dc.new_result("gtsam", args)
    result["setup_seconds_runs"] = []
    try:
        graph = dc.load(args, result)
        factors, with_prior, initial = build(graph, args.se3_info)
        if graph.dim == 3:
            result["se3_info"] = args.se3_info
        result["initial_chi2"] = 2.0 * factors.error(initial)
        result["initial_chi2_g2o"] = chi2_g2o_convention(graph, graph.vertices)
        for _ in range(args.repeat):
            history = []  # (iteration, error_before, error_after), GTSAM's error = chi2 / 2
            params = make_params(args.method, args.max_iterations,
                                 lambda it, before, after: history.append((it, before, after)))
            try:
                t0 = dc.now()
                if args.method == "gn":
                    optimizer = gtsam.GaussNewtonOptimizer(with_prior, initial, params)
                else:
                    optimizer = gtsam.LevenbergMarquardtOptimizer(with_prior, initial, params)
                t_setup = dc.now()
                values = optimizer.optimize()
                t1 = dc.now()
            except RuntimeError as exc:  # e.g. IndeterminateLinearSystemException
                msg = " ".join(str(exc).split())
                # keep the first sentence ("Indeterminate linear system detected ... (Symbol: 160).")
                msg = msg.split(". ")[0].rstrip(".") + "."
                result["error"] = f"{type(exc).__name__}: {msg}"
                result["iterations"] = len(history)
                result["converged"] = False
                break
            result["solve_seconds_runs"].append(t1 - t0)
            result["setup_seconds_runs"].append(t_setup - t0)
            final = 2.0 * factors.error(values)
            iterations = optimizer.iterations()
            # an increase within the relative tolerance (round-off at the optimum) still counts as converged
            if history:
                _, before, after = history[-1]
                increased = (after - before) > dc.RELATIVE_DECREASE_TOL * before
            else:
                increased = False
            gave_up = args.method == "lm" and optimizer.lambda_() >= params.getlambdaUpperBound()
            result.update(
                final_chi2=final,
                final_chi2_g2o=chi2_g2o_convention(
                    graph, {k: from_pose(graph.dim, values.atPose2(k) if graph.dim == 2 else values.atPose3(k))
                            for k in graph.vertices}),
                iterations=iterations,
                converged=(iterations < args.max_iterations and not increased and math.isfinite(final)),
            )
            if increased:
                result["note"] = "stopped because the last step increased the error"
            if gave_up:
                result["note"] = "LM gave up: no decrease even with lambda at its upper bound"
                if iterations == 0:
                    result["converged"] = False
                    result["error"] = "LM made no successful step (every damped solve failed or increased the error)"
                    break
    except Exception as exc:  # report, never crash: the orchestrator reads the JSON
        result["error"] = f"{type(exc).__name__}: {exc}"
        result["converged"] = False
    dc.finish(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
