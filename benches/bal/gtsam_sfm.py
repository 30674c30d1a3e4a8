#!/usr/bin/env python3
"""GTSAM (Python) Levenberg-Marquardt on BAL bundle-adjustment problems: one JSON line per problem.

    gtsam_sfm.py [--rounds 3] [--data DIR] [--prior-sigma 0.1] [--diagonal-damping]
                 [--linear-solver TYPE] [problem ...]

Needs a Python with the `gtsam` wheel from PyPI; written against gtsam 4.3.0 in
~/.cache/factord/venvs/gtsam (python3 -m venv ~/.cache/factord/venvs/gtsam && .../bin/pip install gtsam):
    ~/.cache/factord/venvs/gtsam/bin/python benches/bal/gtsam_sfm.py

The graph is built as in GTSAM's python/gtsam/examples/SFMExample_bal.py: `SfmData.FromBalFile`
(converts BAL's -z-looking, y-up cameras to GTSAM's convention and negates the measured v), one
`GeneralSFMFactorCal3Bundler` per observation with unit isotropic noise (σ = 1 px), so the graph error
is ½Σ‖r‖² in pixels, as in Ceres' bundle_adjuster. Like the example, the gauge is fixed by priors
(σ = 0.1 by default) on camera 0 (all 9 parameters, including f, k1, k2) and point 0. That
over-constrains the problem (12 constraints against a 7-dof gauge) and moves the optimum; use
--prior-sigma 1000 for the unconstrained BAL problem. Costs exclude the prior terms (prior_cost).

GeneralSFMFactor gives a zero residual and Jacobian when a point is behind its camera (Ceres keeps the
residual), so GTSAM minimises a slightly different cost. final_cost is GTSAM's (graph error),
bal_final_cost the BAL/Ceres cost of the same solution with those residuals included, behind_camera
their count. The reference check (within 0.1% of MANIFEST.md's optimum) uses bal_final_cost.

LM uses GTSAM's defaults (λI damping, the default linear solver) except silent, 100 iterations max and
relative error tolerance 1e-6 (Ceres' function_tolerance). solve_seconds is the median over --rounds of
optimize() alone; load_seconds (FromBalFile) and build_seconds (graph + initial values) are separate.
"""
import argparse
import importlib.metadata
import json
import os
import statistics
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import C, P

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
# Reference optima, ½Σ‖r‖² (shared/data/MANIFEST.md).
REFERENCE = {"problem-16-22106-pre.txt": 18033.90, "problem-49-7776-pre.txt": 13344.32}


def build(data, prior_sigma):
    """Projection factors, gauge priors and initial values, as in GTSAM's SFMExample_bal."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    for j in range(data.numberTracks()):
        track = data.track(j)
        for k in range(track.numberMeasurements()):
            i, uv = track.measurement(k)
            graph.add(gtsam.GeneralSFMFactorCal3Bundler(uv, noise, C(i), P(j)))
    priors = gtsam.NonlinearFactorGraph()
    priors.add(gtsam.PriorFactorPinholeCameraCal3Bundler(
        C(0), data.camera(0), gtsam.noiseModel.Isotropic.Sigma(9, prior_sigma)))
    priors.add(gtsam.PriorFactorPoint3(
        P(0), data.track(0).point3(), gtsam.noiseModel.Isotropic.Sigma(3, prior_sigma)))
    initial = gtsam.Values()
    for i in range(data.numberCameras()):
        initial.insert(C(i), data.camera(i))
    for j in range(data.numberTracks()):
        initial.insert(P(j), data.track(j).point3())
    return graph, priors, initial


def bal_cost(data, values):
    """½Σ‖r‖² with no cheirality test (the BAL/Ceres cost), and the number of points behind a camera."""
    cost, behind = 0.0, 0
    cams = [values.atPinholeCameraCal3Bundler(C(i)) for i in range(data.numberCameras())]
    for j in range(data.numberTracks()):
        track, X = data.track(j), values.atPoint3(P(j))
        for k in range(track.numberMeasurements()):
            i, uv = track.measurement(k)
            x, y, z = cams[i].pose().transformTo(X)
            behind += int(z <= 0)
            # Python's Cal3Bundler.uncalibrate drops the distortion in gtsam 4.3.0, so apply it here.
            K, p = cams[i].calibration(), np.array([x / z, y / z])
            n2 = p @ p
            r = K.fx() * (1 + K.k1() * n2 + K.k2() * n2 * n2) * p + [K.px(), K.py()] - uv
            cost += 0.5 * float(r @ r)
    return cost, behind


def run(path, args):
    t = time.perf_counter()
    data = gtsam.SfmData.FromBalFile(path)
    load = time.perf_counter() - t
    t = time.perf_counter()
    proj, priors, initial = build(data, args.prior_sigma)
    graph = gtsam.NonlinearFactorGraph()
    graph.push_back(proj)
    graph.push_back(priors)
    build_s = time.perf_counter() - t

    params = gtsam.LevenbergMarquardtParams()
    params.setVerbosityLM("SILENT")
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-6)
    params.setDiagonalDamping(args.diagonal_damping)
    if args.linear_solver:
        params.setLinearSolverType(args.linear_solver)
    times = []
    for _ in range(args.rounds):
        lm = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        t = time.perf_counter()
        result = lm.optimize()
        times.append(time.perf_counter() - t)

    name = os.path.basename(path)
    bal_initial, behind_initial = bal_cost(data, initial)
    bal_final, behind_final = bal_cost(data, result)
    ref = REFERENCE.get(name)
    return {
        "problem": name, "gtsam": importlib.metadata.version("gtsam"),
        "cameras": data.numberCameras(), "points": data.numberTracks(), "observations": proj.size(),
        "linear_solver": params.getLinearSolverType(), "diagonal_damping": args.diagonal_damping,
        "gauge": f"priors sigma={args.prior_sigma:g} on C(0) (9 params) and P(0) (SFMExample_bal: 0.1)",
        "load_seconds": round(load, 4), "build_seconds": round(build_s, 4),
        "solve_seconds": round(statistics.median(times), 4), "runs": [round(x, 4) for x in times],
        "iterations": lm.iterations(), "hit_max_iterations": lm.iterations() >= params.getMaxIterations(),
        "initial_cost": proj.error(initial), "final_cost": proj.error(result),
        "prior_cost": priors.error(result),
        "bal_initial_cost": bal_initial, "bal_final_cost": bal_final,
        "behind_camera": [behind_initial, behind_final],
        "reference_cost": ref,
        "within_0.1pct": None if ref is None else abs(bal_final - ref) <= 1e-3 * ref,
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("problems", nargs="*")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--data", default=os.path.join(REPO, "..", "shared", "data"))
    p.add_argument("--prior-sigma", type=float, default=0.1, help="gauge prior sigma (example: 0.1)")
    p.add_argument("--diagonal-damping", action="store_true", help="LM damping λ·diag(JᵀJ), not λI")
    p.add_argument("--linear-solver", default="",
                   help="e.g. MULTIFRONTAL_CHOLESKY (GTSAM's default), SEQUENTIAL_CHOLESKY")
    args = p.parse_args()
    problems = args.problems or [os.path.join(args.data, "bal", f) for f in REFERENCE]
    for path in problems:
        print(json.dumps(run(path, args)), flush=True)


if __name__ == "__main__":
    main()
