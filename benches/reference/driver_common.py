"""Command line and result plumbing shared by gtsam_solve.py and g2o_solve.py."""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from typing import Any, Dict, List, Optional

from posegraph_io import PoseGraph, read_pose_graph

# Termination criteria shared by both drivers (see each driver's header for how they map).
RELATIVE_DECREASE_TOL = 1e-6
DEFAULT_MAX_ITERATIONS = 100
DEFAULT_REPEAT = 5


def parse_args(system: str, argv: Optional[List[str]] = None, extra=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=f"{system} pose-graph reference solver (prints one JSON object)")
    p.add_argument("--file", required=True, help="g2o or TORO pose-graph file (or the vertex file of a split pair)")
    p.add_argument("--edges", default=None, help="separate edge file (course ls_slam <name>-e.dat)")
    p.add_argument("--format", choices=["auto", "g2o", "toro"], default="auto",
                   help="2D information order: by record tag (auto; EDGE_SE2=g2o, EDGE2=TORO) or forced")
    p.add_argument("--method", choices=["gn", "lm"], default="gn")
    p.add_argument("--repeat", type=int, default=DEFAULT_REPEAT, help="timed runs, each from the initial guess")
    p.add_argument("--max-iterations", type=int, default=DEFAULT_MAX_ITERATIONS)
    if extra is not None:
        extra(p)
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error("--repeat must be >= 1")
    return args


def new_result(system: str, args: argparse.Namespace) -> Dict[str, Any]:
    return {
        "system": system,
        "method": args.method,
        "file": args.file,
        "edges_file": args.edges,
        "dim": None,
        "poses": None,
        "edges": None,
        "initial_chi2": None,
        "initial_chi2_g2o": None,
        "final_chi2": None,
        "final_chi2_g2o": None,
        "iterations": None,
        "solve_seconds_runs": [],
        "solve_seconds": None,
        "converged": False,
        "error": None,
    }


def load(args: argparse.Namespace, result: Dict[str, Any]) -> PoseGraph:
    graph = read_pose_graph(args.file, args.edges, args.format)
    result.update(dim=graph.dim, poses=len(graph.vertices), edges=len(graph.edges))
    return graph


def finish(result: Dict[str, Any]) -> None:
    """Fill the median and print the JSON object (NaN/inf are written as null)."""
    runs = result["solve_seconds_runs"]
    if runs:
        result["solve_seconds"] = statistics.median(runs)
    for k, v in list(result.items()):
        if isinstance(v, float) and not math.isfinite(v):
            result[k] = None
            if k in ("final_chi2", "final_chi2_g2o"):
                result["converged"] = False
    json.dump(result, sys.stdout)
    sys.stdout.write("\n")
    sys.stdout.flush()


now = time.perf_counter
