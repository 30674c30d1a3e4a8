#!/usr/bin/env python3
"""GTSAM (Python) Levenberg-Marquardt on BAL bundle-adjustment problems: one JSON line per problem.

    gtsam_sfm.py [--rounds 3] [--data DIR] [--linear-solver TYPE] [problem ...]

Run it with a Python that has the `gtsam` wheel (PyPI), e.g. the venv this was written against:
    ~/.cache/factord/venvs/gtsam/bin/python benches/bal/gtsam_sfm.py
(create it with `python3 -m venv ~/.cache/factord/venvs/gtsam && .../bin/pip install gtsam`).

The problem is built the standard GTSAM way, following python/gtsam/examples/SFMExample_bal.py:
`SfmData.FromBalFile` (which converts BAL's -z-looking, y-up cameras to GTSAM's convention and negates
the measured v), one `GeneralSFMFactorCal3Bundler` per observation with a unit isotropic noise model
(σ = 1 px), so graph.error() is ½Σ‖r‖² in pixels, the same cost as Ceres' bundle_adjuster.
Like that example, the gauge is fixed with priors (σ = 0.1) on camera 0 and point 0 at their initial
values; initial_cost/final_cost exclude those two prior terms (prior_cost reports them).
Caveat: GeneralSFMFactor returns a zero residual (and Jacobian) for a point behind its camera, whereas
Ceres' BAL cost keeps it; problem-49 has 31 such observations at the start, so GTSAM's initial cost is
850802.09 instead of 850912.46 (problem-16 has none and matches 4185659.52 exactly).

LM: default GTSAM parameters except silent, 100 iterations max and relative error tolerance 1e-6
(Ceres' function_tolerance). solve_seconds is the median over --rounds of the optimize() call only;
load_seconds (FromBalFile) and build_seconds (graph + initial values) are reported separately.
"""
import argparse
import importlib.metadata
import json
import os
import statistics
import time

import gtsam
from gtsam.symbol_shorthand import C, P

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
# Reference optima, ½Σ‖r‖² (shared/data/MANIFEST.md).
REFERENCE = {"problem-16-22106-pre.txt": 18033.90, "problem-49-7776-pre.txt": 13344.32}


def build(data, prior_sigma=0.1):
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


def run(path, rounds, linear_solver, prior_sigma=0.1):
    t = time.perf_counter()
    data = gtsam.SfmData.FromBalFile(path)
    load = time.perf_counter() - t
    t = time.perf_counter()
    proj, priors, initial = build(data, prior_sigma)
    graph = gtsam.NonlinearFactorGraph()
    graph.push_back(proj)
    graph.push_back(priors)
    build_s = time.perf_counter() - t

    params = gtsam.LevenbergMarquardtParams()
    params.setVerbosityLM("SILENT")
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-6)
    if linear_solver:
        params.setLinearSolverType(linear_solver)
    times = []
    for _ in range(rounds):
        lm = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        t = time.perf_counter()
        result = lm.optimize()
        times.append(time.perf_counter() - t)

    name = os.path.basename(path)
    final = proj.error(result)
    ref = REFERENCE.get(name)
    return {
        "problem": name,
        "gtsam": importlib.metadata.version("gtsam"),
        "cameras": data.numberCameras(), "points": data.numberTracks(), "observations": proj.size(),
        "linear_solver": params.getLinearSolverType(),
        "gauge": f"priors sigma={prior_sigma:g} on C(0) (all 9 camera params) and P(0); SFMExample_bal uses 0.1",
        "load_seconds": round(load, 4), "build_seconds": round(build_s, 4),
        "solve_seconds": round(statistics.median(times), 4), "runs": [round(x, 4) for x in times],
        "iterations": lm.iterations(), "hit_max_iterations": lm.iterations() >= params.getMaxIterations(),
        "initial_cost": proj.error(initial), "final_cost": final, "prior_cost": priors.error(result),
        "reference_cost": ref,
        "within_0.1pct": None if ref is None else abs(final - ref) <= 1e-3 * ref,
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("problems", nargs="*")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--data", default=os.path.join(REPO, "..", "shared", "data"))
    p.add_argument("--linear-solver", default="",
                   help="e.g. MULTIFRONTAL_CHOLESKY (GTSAM's default), SEQUENTIAL_CHOLESKY")
    p.add_argument("--prior-sigma", type=float, default=0.1, help="gauge prior sigma (example: 0.1)")
    args = p.parse_args()
    problems = args.problems or [os.path.join(args.data, "bal", f) for f in REFERENCE]
    for path in problems:
        print(json.dumps(run(path, args.rounds, args.linear_solver, args.prior_sigma)), flush=True)


if __name__ == "__main__":
    main()
