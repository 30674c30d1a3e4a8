#!/usr/bin/env python3
"""g2o reference driver for the factord benchmarks (g2o-python, run with the g2o venv's python).

    python g2o_solve.py --file PATH [--edges PATH] [--format auto|g2o|toro] [--method gn|lm]
                        [--repeat N] [--max-iterations 100]

Prints ONE JSON object on stdout (see driver_common.new_result for the fields).

Problem: parsed by posegraph_io (not by g2o's loader, which registers no types in g2o-python) and
built through the API: VertexSE2/EdgeSE2 (2D) or VertexSE3/EdgeSE3 (3D, Isometry3d from the file's
quaternion).  Gauge: the lowest-id vertex is set_fixed(True).  No robust kernel.
Solver: BlockSolverSE2/SE3 + LinearSolverEigenSE2/SE3 (Eigen SimplicialLDLT, AMD ordering), with
OptimizationAlgorithmGaussNewton (gn) or OptimizationAlgorithmLevenberg (lm, g2o's default lambda
strategy).  The g2o-python 0.0.12 wheel has no CHOLMOD/CSparse solvers; Eigen's simplicial
(non-supernodal) LDLT is fast in 2D but slow on 3D graphs with large fill-in (sphere2500: ~250 ms
per numeric factorisation), so g2o's 3D times here are not representative of g2o+CHOLMOD.

Termination: g2o's own SparseOptimizerTerminateAction (the mechanism behind the g2o CLI's `-gain`)
as a post-iteration action, with gain threshold 1e-6: stop when 0 <= (chi2_prev - chi2)/chi2 < 1e-6
between two consecutive iterations, or after --max-iterations.  LM additionally stops by itself when
no lambda gives a decrease (g2o returns "Terminate"), which counts as converged.  The action costs
one extra error evaluation per iteration (included in the time, as in the g2o CLI).
We deliberately do NOT call optimize(1) in a loop: every optimize() call re-runs the algorithm's
init(), i.e. rebuilds the Hessian structure, redoes the symbolic (AMD) analysis and resets LM's
lambda; that made M3500 GN roughly 2x slower and changes LM's behaviour.

Timing: each of --repeat runs builds a fresh SparseOptimizer from the parsed data (untimed), calls
initialize_optimization() (index mapping / active sets; timed separately as init_seconds_runs,
~3 ms on intel, NOT part of solve_seconds), computes the initial chi2 (untimed), then times
optimize(max_iterations) with time.perf_counter.  optimize() contains everything else: the
Hessian structure, the symbolic AMD analysis, all iterations and the termination checks.
solve_seconds is the median over runs.

chi2: optimizer.chi2() after compute_active_errors(), i.e. sum e^T Omega e with g2o's own error
(2D: t2v(Z^-1 Xi^-1 Xj); 3D: [t; qvec], qvec = imaginary part of the w>=0 error quaternion).
final_chi2_g2o is the same number (field shared with the other drivers).
"""

from __future__ import annotations

import math
import sys

import numpy as np

import g2o

import driver_common as dc
from posegraph_io import PoseGraph


def build_optimizer(graph: PoseGraph, method: str):
    """Fresh optimizer with all vertices/edges; returns (optimizer, objects to keep alive)."""
    opt = g2o.SparseOptimizer()
    if graph.dim == 2:
        solver = g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())
    else:
        solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    if method == "gn":
        algorithm = g2o.OptimizationAlgorithmGaussNewton(solver)
    else:
        algorithm = g2o.OptimizationAlgorithmLevenberg(solver)
    opt.set_algorithm(algorithm)

    gauge = graph.first_vertex
    for vid, p in graph.vertices.items():
        if graph.dim == 2:
            v = g2o.VertexSE2()
            v.set_estimate(g2o.SE2(*p))
        else:
            v = g2o.VertexSE3()
            v.set_estimate(g2o.Isometry3d(g2o.Quaternion(p[6], p[3], p[4], p[5]), np.array(p[:3])))
        v.set_id(vid)
        v.set_fixed(vid == gauge)
        opt.add_vertex(v)

    for e in graph.edges:
        m = e.measurement
        if graph.dim == 2:
            edge = g2o.EdgeSE2()
            edge.set_measurement(g2o.SE2(*m))
        else:
            edge = g2o.EdgeSE3()
            edge.set_measurement(g2o.Isometry3d(g2o.Quaternion(m[6], m[3], m[4], m[5]), np.array(m[:3])))
        edge.set_vertex(0, opt.vertex(e.i))
        edge.set_vertex(1, opt.vertex(e.j))
        edge.set_information(np.array(e.information, dtype=float))
        opt.add_edge(edge)
    return opt, (solver, algorithm)


def chi2(opt) -> float:
    opt.compute_active_errors()
    return float(opt.chi2())


def main() -> int:
    args = dc.parse_args("g2o")
    result = dc.new_result("g2o", args)
    result["init_seconds_runs"] = []
    try:
        graph = dc.load(args, result)
        for _ in range(args.repeat):
            opt, keep_alive = build_optimizer(graph, args.method)
            terminate = g2o.SparseOptimizerTerminateAction()
            terminate.set_gain_threshold(dc.RELATIVE_DECREASE_TOL)
            terminate.set_max_iterations(args.max_iterations)
            opt.add_post_iteration_action(terminate)

            t0 = dc.now()
            ok_init = opt.initialize_optimization()
            t1 = dc.now()
            # initial chi2 needs the active edge set; evaluated outside the timed region
            initial = chi2(opt)
            t2 = dc.now()
            iterations = opt.optimize(args.max_iterations)
            t3 = dc.now()

            result["init_seconds_runs"].append(t1 - t0)
            result["solve_seconds_runs"].append(t3 - t2)
            final = chi2(opt)
            result.update(initial_chi2=initial, initial_chi2_g2o=initial,
                          final_chi2=final, final_chi2_g2o=final, iterations=iterations)
            if not ok_init:
                result["error"] = "initialize_optimization() failed"
            elif iterations == 0:
                result["error"] = "g2o optimize() reported failure (a linear solve failed)"
            result["converged"] = (result["error"] is None and math.isfinite(final)
                                   and iterations < args.max_iterations)
            del keep_alive
    except Exception as exc:  # report, never crash: the orchestrator reads the JSON
        result["error"] = f"{type(exc).__name__}: {exc}"
        result["converged"] = False
    dc.finish(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
