#!/usr/bin/env python3
"""GTSAM iSAM2 on a streaming 2D or 3D pose graph: per-step latency, final chi2, peak memory.

    isam2_stream.py <g2o file> [--json out.json] [--dump-latencies f] [--limit N]
                    [--relinearize-threshold 0.1] [--relinearize-skip 10]

Run it with the gtsam venv's python (benches/reference/setup.sh creates it):
    ~/.cache/factord/venvs/gtsam/bin/python benches/incremental/isam2_stream.py \
        /work/shared/data/2d/carlone/input_M3500_g2o.g2o

The file is parsed by benches/reference/posegraph_io.py, the reader the batch reference drivers use.
2D (VERTEX_SE2/EDGE_SE2, or TORO VERTEX2/EDGE2) and 3D (VERTEX_SE3:QUAT/EDGE_SE3:QUAT) graphs.

3D: Pose3 and BetweenFactorPose3. The file's 6x6 information is in the order (t, R) and applies
to g2o's error [t; qvec], qvec about half the rotation angle (MANIFEST.md); GTSAM's error is
Logmap = (omega, V^-1 t) with the whole angle. So, as factord's reader and the batch reference
(gtsam_solve.py --se3-info g2o) do, the rotation rows and columns are scaled by 1/2
(D Omega D, D = diag(1,1,1,1/2,1/2,1/2)) and then the blocks are swapped to GTSAM's (R, t)
order: all three minimise the same cost up to O(theta^3) per edge.

Streaming protocol
------------------
Vertices are processed in increasing id order (with --limit N, only the first N ids and the edges
among them).  Step k:
  1. new factors = every edge (i, j) whose larger endpoint max(i, j) is k, i.e. the edges that
     become complete when pose k arrives, as BetweenFactorPose2 with the file's full 3x3
     information matrix (gtsam.noiseModel.Gaussian.Information).  The first pose also gets a
     PriorFactorPose2 at its file value with sigma 1e-6 on x, y and theta (the gauge; it is a
     prior, not a hard constraint).
  2. initial guess for pose k = previous estimate of pose j composed with the edge measurement,
     where the edge is the one between k and the previous vertex (odometry), or failing that any
     new edge to an already-present pose (measurement inverted if the edge is stored as (k, j));
     a pose with no such edge gets the file's vertex value (3D: the same with Pose3).  The number of poses initialised
     each way is reported in "initial_guess".
  3. isam.update(new_factors, new_values), then isam.calculateEstimate(): the full estimate is
     available after every step, and it is the "previous estimate" used by the next step.
The timed region of a step (time.perf_counter) is all of 1-3: building the factors and values,
update and estimate.  Parsing the file and grouping the edges by step happen before the loop and
are not timed.  total_seconds is the sum of the per-step times; percentiles are numpy's linear
interpolation over the per-step times.

iSAM2: ISAM2Params() defaults (Gauss-Newton, CHOLESKY, wildfire 0.001) except the relinearize
threshold and skip, which default to GTSAM's own 0.1 and 10 and can be changed by the flags
(issue 16's acceptance runs use 0.1 and 1: acceptance.py passes --relinearize-skip 1).

peak_rss_kb: VmHWM of this process (/proc/self/status) at the end of the stream, before the
batch reference solves: the interpreter, gtsam and the stream's state.

chi2 (prior excluded; no 1/2):
  final_chi2      2 * graph.error(estimate) over all streamed edges = sum e^T Omega e with GTSAM's
                  Pose2 between error e = Logmap(Z^-1 Xi^-1 Xj) = (V(theta)^-1 t, theta).
  final_chi2_t2v  the same estimate in g2o's / factord's convention, e = t2v(Z^-1 Xi^-1 Xj)
                  (posegraph_io.chi2_g2o_convention).  It differs slightly from final_chi2
                  because the translation part of Logmap is not t2v's.
  batch_chi2      the same two numbers after a plain GaussNewtonOptimizer on the full graph (with
  batch_chi2_t2v  the same prior) from the file's initial values: the batch optimum, for reference.
  batch_from_isam2_chi2   GaussNewtonOptimizer started from the final iSAM2 estimate instead.
  chi2_gap        final_chi2 / min(batch_chi2, batch_from_isam2_chi2) - 1 (GTSAM's convention).
  3D: final_chi2 and batch_chi2 use GTSAM's Logmap error with D Omega D (see above);
  final_chi2_t2v / batch_chi2_t2v are then g2o's [t; qvec] cost with the file's information.
Batch GN settings are those of benches/reference/gtsam_solve.py (relative tolerance 1e-6,
absolute 1e-9, at most 100 iterations, MULTIFRONTAL_CHOLESKY).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import sys
import time
from typing import Dict, List, Tuple

import numpy as np

import gtsam

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "reference"))
from posegraph_io import Edge, PoseGraph, chi2_g2o_convention, read_pose_graph  # noqa: E402

PRIOR_SIGMA = 1e-6
# The other robots' first poses (--robots), by dimension: weak, so they hardly bias the optimum,
# yet not so weak that iSAM2 calls the system indeterminate beside the gauge prior (σ 1e3 did in
# 2D, σ 10 in 3D).
OTHER_ROBOT_PRIOR_SIGMA = {2: 10.0, 3: 1.0}


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description="GTSAM iSAM2 streaming pose-graph benchmark (prints one JSON object)")
    p.add_argument("file", help="2D g2o (VERTEX_SE2/EDGE_SE2), TORO, or 3D g2o (SE3:QUAT) pose-graph file")
    p.add_argument("--json", metavar="OUT", help="also write the JSON object to this file")
    p.add_argument("--dump-latencies", metavar="FILE", help="write one step latency (ms) per line")
    p.add_argument("--limit", type=int, metavar="N", help="stream only the first N poses (lowest ids)")
    p.add_argument("--relinearize-threshold", type=float, default=0.1, help="ISAM2Params relinearizeThreshold (0.1)")
    p.add_argument("--relinearize-skip", type=int, default=10, help="ISAM2Params relinearizeSkip (10)")
    p.add_argument("--robots", type=int, default=1,
                   help="cut the poses into R contiguous robots streamed interleaved, as "
                        "benches/robots/split.py sends them (1: the file's order)")
    args = p.parse_args()
    if args.limit is not None and args.limit < 1:
        p.error("--limit must be >= 1")
    return args


def restrict(graph: PoseGraph, limit: int | None) -> PoseGraph:
    """The first `limit` poses (by id) and the edges among them."""
    ids = sorted(graph.vertices)[:limit]
    keep = set(ids)
    return PoseGraph(graph.dim, {k: graph.vertices[k] for k in ids},
                     [e for e in graph.edges if e.i in keep and e.j in keep])


def edges_by_step(graph: PoseGraph, order: List[int]) -> Dict[int, List[Edge]]:
    """Vertex id -> the edges whose later-arriving endpoint (in `order`) is that id (file order
    kept)."""
    arrival = {k: n for n, k in enumerate(order)}
    steps: Dict[int, List[Edge]] = {k: [] for k in graph.vertices}
    for e in graph.edges:
        steps[max(e.i, e.j, key=arrival.__getitem__)].append(e)
    return steps


def interleaved(ids: List[int], robots: int) -> Tuple[List[int], Dict[int, int]]:
    """The arrival order of `robots` contiguous robots streamed round by round (every robot's
    pose t, then pose t + 1, ...), as benches/robots/split.py sends them, and each id's robot.
    One robot: the ids in order."""
    n = len(ids)
    owner = {k: min(robots - 1, pos * robots // n) for pos, k in enumerate(ids)}
    mine: Dict[int, List[int]] = {}
    for k in ids:
        mine.setdefault(owner[k], []).append(k)
    order = [poses[t] for t in range(max(len(p) for p in mine.values()))
             for r, poses in sorted(mine.items()) if t < len(poses)]
    return order, owner


HALF_ANGLE = np.outer([1.0, 1.0, 1.0, 0.5, 0.5, 0.5], [1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
SWAP_T_R = [3, 4, 5, 0, 1, 2]  # (t, R) <-> (R, t)


def to_pose(p):
    """A file value or measurement as a gtsam pose: (x, y, theta) or (x, y, z, qx, qy, qz, qw)."""
    if len(p) == 3:
        return gtsam.Pose2(*p)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(p[6], p[3], p[4], p[5]), np.array(p[:3], dtype=float))


def between_factor(e: Edge):
    info = np.array(e.information, dtype=float)
    if len(e.measurement) == 3:
        noise = gtsam.noiseModel.Gaussian.Information(info)
        return gtsam.BetweenFactorPose2(e.i, e.j, to_pose(e.measurement), noise)
    info = (info * HALF_ANGLE)[np.ix_(SWAP_T_R, SWAP_T_R)]
    noise = gtsam.noiseModel.Gaussian.Information(info)
    return gtsam.BetweenFactorPose3(e.i, e.j, to_pose(e.measurement), noise)


def at(values: gtsam.Values, k: int, dim: int):
    return values.atPose2(k) if dim == 2 else values.atPose3(k)


def initial_guess(k: int, prev: int | None, new_edges: List[Edge], estimate: gtsam.Values,
                  file_value, dim: int) -> Tuple[object, str]:
    """Initial value of pose k and how it was obtained ('odometry', 'other edge' or 'file')."""
    chosen, how = None, None
    for e in new_edges:
        other = e.i if e.j == k else e.j
        if other == k:  # self-loop: says nothing about where k is
            continue
        if other == prev:
            chosen, how = e, "odometry"
            break
        if chosen is None:
            chosen, how = e, "other edge"
    if chosen is None:
        return to_pose(file_value), "file"
    z = to_pose(chosen.measurement)  # z = X_i^-1 X_j
    if chosen.j == k:
        return at(estimate, chosen.i, dim).compose(z), how
    return at(estimate, chosen.j, dim).compose(z.inverse()), how


def batch_gn(factors: gtsam.NonlinearFactorGraph, prior,
             start: gtsam.Values) -> Tuple[gtsam.Values, int]:
    """Plain Gauss-Newton on the full graph plus the gauge prior (gtsam_solve.py's settings)."""
    graph = gtsam.NonlinearFactorGraph(factors)
    graph.add(prior)
    params = gtsam.GaussNewtonParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    params.setErrorTol(0.0)
    params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
    optimizer = gtsam.GaussNewtonOptimizer(graph, start, params)
    values = optimizer.optimize()
    return values, optimizer.iterations()


def as_tuples(values: gtsam.Values, ids, dim: int) -> Dict[int, Tuple[float, ...]]:
    out = {}
    for k in ids:
        if dim == 2:
            p = values.atPose2(k)
            out[k] = (p.x(), p.y(), p.theta())
        else:
            p = values.atPose3(k)
            q, t = p.rotation().toQuaternion(), p.translation()
            out[k] = (t[0], t[1], t[2], q.x(), q.y(), q.z(), q.w())
    return out


def peak_rss_kb() -> int | None:
    """VmHWM (peak resident set, kB) of this process."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def emit(args, result: dict, ms: np.ndarray) -> int:
    """Prints the report (and writes it to --json), and the latencies to --dump-latencies."""
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    if args.dump_latencies:
        with open(args.dump_latencies, "w") as fh:
            fh.writelines(f"{v:.6f}\n" for v in ms)
    return 0


def stream_report(args, graph: PoseGraph, ms: np.ndarray, peak_kb) -> dict:
    """What every report has: the dataset, the updates answered and their latencies (ms)."""
    some = len(ms) > 0
    return {
        "system": "gtsam-isam2",
        "gtsam_version": importlib.metadata.version("gtsam"),
        "dataset": os.path.splitext(os.path.basename(args.file))[0],
        "file": os.path.abspath(args.file),
        "limit": args.limit,
        "steps": len(ms),
        "robots": args.robots,
        "edges": len(graph.edges),
        "total_seconds": float(ms.sum() / 1e3),
        "mean_ms": float(ms.mean()) if some else None,
        "p50_ms": float(np.percentile(ms, 50)) if some else None,
        "p90_ms": float(np.percentile(ms, 90)) if some else None,
        "p99_ms": float(np.percentile(ms, 99)) if some else None,
        "max_ms": float(ms.max()) if some else None,
        "dim": graph.dim,
        "peak_rss_kb": peak_kb,
        "relinearize_threshold": args.relinearize_threshold,
        "relinearize_skip": args.relinearize_skip,
    }


def write_failure(args, graph: PoseGraph, latencies: list, peak_kb, failure: dict) -> int:
    """The report of a stream GTSAM could not finish: the updates answered until it failed (no
    chi2: the estimate is the last one before the failure and no batch solve is attempted)."""
    ms = np.array(latencies) * 1e3
    result = {**stream_report(args, graph, ms, peak_kb), "chi2_gap": None, **failure}
    return emit(args, result, ms)


def main() -> int:
    args = parse_args()
    full = read_pose_graph(args.file)
    graph = restrict(full, args.limit)
    dim = graph.dim
    ids, owner = interleaved(sorted(graph.vertices), args.robots)
    steps = edges_by_step(graph, ids)
    first = ids[0]
    # Each robot's first pose gets a prior: the first robot's fixes the gauge; the others' are
    # weak (OTHER_ROBOT_PRIOR_SIGMA) and at the pose's place in the file's frame, which iSAM2
    # must be given (factord's session finds each robot's frame from the closures instead).
    firsts = {}
    for k in ids:
        firsts.setdefault(owner[k], k)
    robot_firsts = set(firsts.values())
    previous_of_robot: Dict[int, int] = {}

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(args.relinearize_threshold)
    params.relinearizeSkip = args.relinearize_skip
    isam = gtsam.ISAM2(params)
    prior_cls = gtsam.PriorFactorPose2 if dim == 2 else gtsam.PriorFactorPose3
    prior = prior_cls(first, to_pose(graph.vertices[first]),
                      gtsam.noiseModel.Isotropic.Sigma(3 if dim == 2 else 6, PRIOR_SIGMA))

    # ---- the stream -------------------------------------------------------------------------
    latencies = []
    guess_sources = {"odometry": 0, "other edge": 0, "file": 0}
    estimate = gtsam.Values()
    prev = None
    for k in ids:
        t0 = time.perf_counter()
        new_factors = gtsam.NonlinearFactorGraph()
        if k == first:
            new_factors.add(prior)
        elif k in robot_firsts:
            new_factors.add(prior_cls(k, to_pose(graph.vertices[k]),
                                      gtsam.noiseModel.Isotropic.Sigma(3 if dim == 2 else 6, OTHER_ROBOT_PRIOR_SIGMA[dim])))
        for e in steps[k]:
            new_factors.add(between_factor(e))
        prev = previous_of_robot.get(owner[k])
        pose, how = initial_guess(k, prev, steps[k], estimate, graph.vertices[k], dim)
        new_values = gtsam.Values()
        new_values.insert(k, pose)
        try:
            isam.update(new_factors, new_values)
            estimate = isam.calculateEstimate()
        except RuntimeError as exc:
            # GTSAM gave up (e.g. IndeterminateSystemException): the stream ends here, and the
            # report says so with the latencies of the updates that were answered.
            failure = {"failed_at_pose": k, "error": str(exc).strip().splitlines()[0]}
            break
        latencies.append(time.perf_counter() - t0)
        guess_sources[how] += 1
        previous_of_robot[owner[k]] = k
    else:
        failure = None
    peak_kb = peak_rss_kb()
    if failure is not None:
        return write_failure(args, graph, latencies, peak_kb, failure)

    # ---- chi2 of the final estimate and of the batch optimum (not timed) ----------------------
    factors = gtsam.NonlinearFactorGraph()
    for e in graph.edges:
        factors.add(between_factor(e))
    file_values = gtsam.Values()
    for k in ids:
        file_values.insert(k, to_pose(graph.vertices[k]))
    batch, batch_iterations = batch_gn(factors, prior, file_values)
    polished, polished_iterations = batch_gn(factors, prior, estimate)

    ms = np.array(latencies) * 1e3
    final_chi2 = 2.0 * factors.error(estimate)
    batch_chi2 = 2.0 * factors.error(batch)
    polished_chi2 = 2.0 * factors.error(polished)
    result = {
        **stream_report(args, graph, ms, peak_kb),
        "final_chi2": final_chi2,
        "final_chi2_t2v": chi2_g2o_convention(graph, as_tuples(estimate, ids, dim)),
        "batch_chi2": batch_chi2,
        "batch_chi2_t2v": chi2_g2o_convention(graph, as_tuples(batch, ids, dim)),
        "batch_iterations": batch_iterations,
        "batch_from_isam2_chi2": polished_chi2,
        "chi2_gap": final_chi2 / min(batch_chi2, polished_chi2) - 1.0,
        "batch_from_isam2_iterations": polished_iterations,
        "initial_chi2_file": 2.0 * factors.error(file_values),
        "prior": "prior sigma 1e-6",
        "factorization": str(params.getFactorization()),
        "initial_guess": guess_sources,
        "timed": "per step: build factors+values, isam.update, isam.calculateEstimate",
    }
    return emit(args, result, ms)


if __name__ == "__main__":
    sys.exit(main())
