#!/usr/bin/env python3
"""GTSAM's GncLMOptimizer on a g2o pose graph with possibly wrong loop closures (issue 54's
benchmark; run with the gtsam venv's python).

    python gtsam_gnc.py --file CORRUPTED.g2o --out SOLVED.g2o [--loss gm|tls]

Problem as gtsam_solve.py builds it (posegraph_io, the file's information, a 1e-6 prior on the
lowest pose). Known inliers: the prior and every edge between consecutive ids (odometry), as the
issue's measurement did; every other edge is left to GNC. Initial values: the file's vertices
(odometry composition for the benchmark files). GTSAM's defaults otherwise (Geman-McClure unless
--loss tls, barcSq = 1, mu step 1.4, LM inner solver). Writes the optimised VERTEX lines to --out
and prints one JSON object: seconds (optimize() only), iterations, rejected_lines (line numbers
in the input of the edges whose final weight is below 0.5).
"""
import argparse
import json
import sys
import time

import gtsam

from gtsam_solve import build, from_pose
from posegraph_io import read_pose_graph


def edge_lines(path):
    numbers = []
    for number, line in enumerate(open(path), start=1):
        tag = line.split()[:1]
        if tag and tag[0] in ("EDGE_SE2", "EDGE_SE3:QUAT", "EDGE2"):
            numbers.append(number)
    return numbers


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--file", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--loss", choices=["gm", "tls"], default="gm")
    a = p.parse_args()
    graph = read_pose_graph(a.file)
    _, with_prior, initial = build(graph, "file")
    lines = edge_lines(a.file)
    known = [k for k, e in enumerate(graph.edges) if abs(e.i - e.j) == 1]
    known.append(len(graph.edges))  # the gauge prior, added last by build()
    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setKnownInliers(known)
    if a.loss == "tls":
        params.setLossType(gtsam.GncLossType.TLS)
    start = time.perf_counter()
    optimizer = gtsam.GncLMOptimizer(with_prior, initial, params)
    result = optimizer.optimize()
    seconds = time.perf_counter() - start
    weights = optimizer.getWeights()
    rejected = [lines[k] for k in range(len(graph.edges)) if weights[k] < 0.5]
    with open(a.out, "w") as out:
        for vid in sorted(graph.vertices):
            pose = result.atPose2(vid) if graph.dim == 2 else result.atPose3(vid)
            v = from_pose(graph.dim, pose)
            tag = "VERTEX_SE2" if graph.dim == 2 else "VERTEX_SE3:QUAT"
            out.write("%s %d %s\n" % (tag, vid, " ".join(repr(float(x)) for x in v)))
    print(json.dumps({"seconds": seconds, "rejected_lines": rejected, "loss": a.loss}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
