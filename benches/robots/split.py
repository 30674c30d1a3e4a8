#!/usr/bin/env python3
"""Many robots, one map (issue 54): a dataset's pose sequence cut into R contiguous robots, each
in its own start frame, streamed interleaved into one session created with ``robots``.

    python3 split.py --factord target/release/factord --data-dir ../shared/data \
        [--dataset 2d/carlone/input_M3500_g2o.g2o] [--robots 2 4 8] [--transport http|zenoh] \
        [--wrong 0.2 --wrong-kind random|aliasing] [--seed 1]

Robot r gets poses [r·n/R, (r+1)·n/R) of the file, renamed ``robot_key(chr(ord('a')+r), i)``;
its values are the file's initial guess expressed in its first pose's frame (what its odometry
would say), edges within a robot are its odometry and own closures, edges across robots are
inter-robot closures. Round t sends every robot's pose t with the edges whose later endpoint
(by arrival) it is; closures to a robot's pose that has not arrived wait until it has.

``--wrong F`` adds F times as many wrong inter-robot closures as there are right ones:
``random`` between uniform pose pairs of two robots with a uniform measurement (±20 m, any
angle); ``aliasing`` in groups of 5-20 consecutive closures that agree with each other (all
measured as if the other robot's poses were moved by one rigid transform, 5-20 m and up to a
radian) but not with the map.

Reported (one JSON line per split): whether every robot ended in the map, closures held /
rejected, merges and the time deciding them, update p50/p99/worst (batch round trip), total
time, the final chi2 against the clean single-robot optimum (relative), and the position RMSE
after alignment against that optimum, and with wrong closures the precision and recall of the
closures kept out of the map (held or rejected at the end). The clean optimum is ``factord
solve`` on the file.

``--wait`` sends every batch with ``wait=true``: its latency is then until the estimate
reflects it (acknowledgement and solve), the measure an iSAM2 update with its estimate is
(``benches/incremental/isam2_stream.py --robots R`` streams the same interleaving into GTSAM).

``--outliers auto`` creates the session with ``outliers: auto`` (every loop closure held out
until found consistent, docs/guide/wrong-closures.md); ``--robots 1`` streams the whole file as
one robot, with wrong closures among its loop closures. Then also reported: ``streamed_rmse_m``
and ``gate_precision``/``gate_recall``, read 0.2 s after the stream (the gate's work alone:
a consolidation waits for 0.5 s of rest), and ``optimize_s``, the closing ``optimize`` (a full
solve: it consolidates every candidate by graduated non-convexity).
"""
import math
import random
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "outliers"))
sys.path.insert(0, str(HERE.parent.parent / "clients" / "python"))
sys.path.insert(0, str(HERE.parent.parent / "clients" / "python" / "tests"))

from evaluate import aligned_rmse  # noqa: E402
from factord_client import HttpClient, ZenohClient, g2o, robot_key  # noqa: E402
from factord_client.geometry import Pose2, pose_from_wire  # noqa: E402
import test_recovery as harness  # noqa: E402  (Server: factord serve on free ports)


def percentile(values, p):
    s = sorted(values)
    return s[min(len(s) - 1, int(p / 100 * len(s)))] if s else float("nan")


def clean_optimum(factord, path):
    out = tempfile.mktemp(suffix=".g2o")
    run = subprocess.run([factord, "solve", str(path), "--out", out, "--summary-json", "-",
                          "--quiet"], capture_output=True, text=True, check=True)
    chi2 = json.loads(run.stdout)["final_chi2"]
    positions, optimum = {}, {}
    for line in open(out):
        f = line.split()
        if f and f[0] in ("VERTEX_SE2", "VERTEX_SE3:QUAT"):
            p = [float(x) for x in f[2:]]
            positions[int(f[1])] = (p[0], p[1], p[2] if f[0] != "VERTEX_SE2" else 0.0)
            optimum[int(f[1])] = p
    os.unlink(out)
    return chi2, positions, optimum


def owners(graph, robots):
    ids = sorted(graph.vertices)
    return {vid: min(robots - 1, pos * robots // len(ids)) for pos, vid in enumerate(ids)}


def wrong_closures(graph, robots, optimum, fraction, kind, rng):
    """Wrong inter-robot closures (g2o.Edge, ``line`` = -1), ``fraction`` × the right ones."""
    owner = owners(graph, robots)
    # Among inter-robot closures; with one robot, among its loop closures.
    right = [e for e in graph.edges
             if owner[e.i] != owner[e.j] or (robots == 1 and abs(e.i - e.j) != 1)]
    info = right[0].information if right else graph.edges[0].information
    by_robot = {}
    for vid in sorted(graph.vertices):
        by_robot.setdefault(owner[vid], []).append(vid)
    target = int(round(fraction * len(right)))
    kind_name = graph.variable_kind
    pose = lambda vid: pose_from_wire(kind_name, optimum[vid])  # noqa: E731
    out = []
    while len(out) < target:
        r, s = rng.sample(range(robots), 2) if robots > 1 else (0, 0)
        if kind == "random":
            i, j = rng.choice(by_robot[r]), rng.choice(by_robot[s])
            if abs(i - j) <= 1:
                continue  # a loop closure joins poses that are not consecutive
            z = [rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-math.pi, math.pi)]
            if graph.dimension == 3:
                z = random_pose3(rng, 20.0, math.pi).to_wire()
            out.append(g2o.Edge(i, j, list(z), list(info), [], line=-1))
            continue
        size = rng.randint(5, 20)
        a, b = by_robot[r], by_robot[s]
        if len(a) <= size or len(b) <= size:
            continue
        i0, j0 = rng.randrange(len(a) - size), rng.randrange(len(b) - size)
        shift = random_shift(graph.dimension, rng)
        for m in range(min(size, target - len(out))):
            i, j = a[i0 + m], b[j0 + m]
            z = pose(i).inverse().compose(shift.compose(pose(j))).to_wire()
            out.append(g2o.Edge(i, j, list(z), list(info), [], line=-1))
    return out


def random_shift(dimension, rng):
    """A rigid transform 5-20 m away, turned by up to a radian."""
    d, a = rng.uniform(5, 20), rng.uniform(0, 2 * math.pi)
    if dimension == 2:
        return Pose2(d * math.cos(a), d * math.sin(a), rng.uniform(-1, 1))
    return random_pose3(rng, d, 1.0)


def random_pose3(rng, distance, angle):
    axis = [rng.gauss(0, 1) for _ in range(3)]
    n = math.sqrt(sum(c * c for c in axis))
    half = rng.uniform(-angle, angle) / 2
    q = [math.sin(half) * c / n for c in axis] + [math.cos(half)]
    t = [rng.uniform(-distance, distance) for _ in range(3)]
    return pose_from_wire("se3", t + q)


def split_batches(graph, robots, extra=()):
    """Per round, one batch per robot: (robot, batch). Keys map file id -> (robot, index)."""
    ids = sorted(graph.vertices)
    n = len(ids)
    owner = {}
    for pos, vid in enumerate(ids):
        r = min(robots - 1, pos * robots // n)
        owner[vid] = r
    starts = {}
    for vid in ids:
        starts.setdefault(owner[vid], vid)
    local = {vid: vid - starts[owner[vid]] for vid in ids}
    key = {vid: robot_key(chr(ord("a") + owner[vid]), local[vid]) for vid in ids}
    kind = graph.variable_kind
    origin = {r: pose_from_wire(kind, graph.vertices[v]).inverse() for r, v in starts.items()}
    # Arrival round of a vertex: its index within its robot.
    arrival = local
    by_round = {}
    for e in list(graph.edges) + list(extra):
        t = max(arrival[e.i], arrival[e.j])
        # An edge is sent by the robot whose pose arrives last (ties: the later id's robot).
        sender = owner[e.i] if (arrival[e.i], e.i) > (arrival[e.j], e.j) else owner[e.j]
        by_round.setdefault((t, sender), []).append(e)
    rounds = []
    for t in range(max(local.values()) + 1):
        row = []
        for r in range(robots):
            vid = starts[r] + t
            if vid not in graph.vertices or owner.get(vid) != r:
                if (t, r) not in by_round:
                    continue
                variables = []
            else:
                value = origin[r].compose(pose_from_wire(kind, graph.vertices[vid])).to_wire()
                variables = [{"key": key[vid], "kind": kind, "value": list(value)}]
            edges = by_round.get((t, r), [])
            factors = [{"type": graph.factor_type, "keys": [key[e.i], key[e.j]],
                        "measurement": list(e.measurement), "information": list(e.information)}
                       for e in edges]
            wrong = [e.line == -1 for e in edges]
            row.append((r, {"variables": variables, "factors": factors}, wrong))
        rounds.append(row)
    return rounds, key


def run_split(args, graph, robots, clean_chi2, clean_positions, optimum):
    rng = random.Random(args.seed * 1000 + robots)
    extra = (wrong_closures(graph, robots, optimum, args.wrong, args.wrong_kind, rng)
             if args.wrong > 0 else [])
    rounds, key = split_batches(graph, robots, extra)
    wrong_ids = set()
    root = Path(tempfile.mkdtemp(prefix="robots-bench-"))
    server = harness.Server(args.factord, root, "main").start()
    try:
        http = HttpClient(server.http, timeout=120)
        session = f"split{robots}"
        options = {"robots": {"min_closures": args.min_closures}} if robots > 1 else {}
        if args.outliers:
            options["outliers"] = args.outliers
        http.create_session(graph.session_kind, session=session, **options)
        zenoh = ZenohClient(server.zenoh, timeout=60) if args.transport == "zenoh" else None
        latencies = []
        t0 = time.monotonic()
        for row in rounds:
            for r, batch, wrong in row:
                b0 = time.monotonic()
                if zenoh is not None:
                    ack = zenoh.apply_batch(session, batch, wait=args.wait)
                else:
                    ack = http.apply_batch(session, batch, wait=args.wait)
                latencies.append(time.monotonic() - b0)
                wrong_ids.update(i for i, w in zip(ack["factor_ids"], wrong) if w)
        total = time.monotonic() - t0
        if args.dump_latencies:
            Path(f"{args.dump_latencies}-{robots}.txt").write_text(
                "".join(f"{s * 1e3:.4f}\n" for s in latencies))
        # The stream's last solves land; a consolidation waits for 0.5 s of rest, so what is
        # read here is the gate's work alone.
        time.sleep(0.2)
        streamed_rmse = rmse_of(http.estimate(session), key, graph, clean_positions)
        gated = http.outliers(session) if args.outliers else None
        # A client's optimize is a full solve, which consolidates every candidate.
        c0 = time.monotonic()
        stats = http.optimize(session, wait=True)["stats"]
        consolidate_s = time.monotonic() - c0
        report = http.robots(session) if robots > 1 else {
            "robots": [{"in_map": True}], "merges": [], "pending": [], "rejected": [],
            "admitted": 0}
        outliers = http.outliers(session) if args.outliers else {"pending": [], "rejected": []}
        rmse = rmse_of(http.estimate(session), key, graph, clean_positions)
        merges = report["merges"]
        outside = {c["factor_id"] for c in report["pending"] + report["rejected"]
                   + outliers["pending"] + outliers["rejected"]}
        caught = len(outside & wrong_ids)
        gate_out = ({c["factor_id"] for c in gated["pending"] + gated["rejected"]}
                    if gated else set())
        gate_caught = len(gate_out & wrong_ids)
        return {
            "dataset": args.dataset, "robots": robots, "transport": args.transport, "wait": args.wait,
            "min_closures": args.min_closures,
            "all_in_map": all(r["in_map"] for r in report["robots"]),
            "pending": len(report["pending"]), "rejected": len(report["rejected"]),
            "merges": len(merges),
            "merge_decide_ms_max": round(max((m["seconds"] for m in merges), default=0) * 1e3, 3),
            "updates": len(latencies),
            "update_p50_ms": round(percentile(latencies, 50) * 1e3, 3),
            "update_p99_ms": round(percentile(latencies, 99) * 1e3, 3),
            "update_worst_ms": round(max(latencies) * 1e3, 3),
            "total_s": round(total, 3),
            "chi2": stats["chi2"], "clean_chi2": clean_chi2,
            "chi2_rel": abs(stats["chi2"] - clean_chi2) / clean_chi2,
            "rmse_m": rmse, "streamed_rmse_m": streamed_rmse,
            "outliers": args.outliers, "optimize_s": round(consolidate_s, 3),
            "gate_precision": gate_caught / len(gate_out) if gate_out else 1.0,
            "gate_recall": gate_caught / len(wrong_ids) if wrong_ids else 1.0,
            "consolidations": outliers.get("consolidations"),
            "wrong": len(wrong_ids), "wrong_kind": args.wrong_kind if wrong_ids else None,
            "admitted": report["admitted"], "kept_out": len(outside),
            "precision": caught / len(outside) if outside else 1.0,
            "recall": caught / len(wrong_ids) if wrong_ids else 1.0,
        }
    finally:
        server.kill()


def rmse_of(estimate, key, graph, clean_positions):
    by_key = {v["key"]: v["value"] for v in estimate["variables"]}
    positions = {}
    for vid, k in key.items():
        if k in by_key:
            v = by_key[k]
            positions[vid] = (v[0], v[1], v[2] if graph.dimension == 3 else 0.0)
    return aligned_rmse(clean_positions, positions)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--factord", required=True)
    parser.add_argument("--data-dir", type=Path, required=True)
    parser.add_argument("--dataset", default="2d/carlone/input_M3500_g2o.g2o")
    parser.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--transport", choices=["http", "zenoh"], default="http")
    parser.add_argument("--wait", action="store_true",
                        help="each batch answered once the estimate reflects it (wait=true): the "
                             "update latency is then acknowledgement and solve, as an iSAM2 "
                             "update with its estimate")
    parser.add_argument("--min-closures", type=int, default=3)
    parser.add_argument("--wrong", type=float, default=0.0)
    parser.add_argument("--wrong-kind", choices=["random", "aliasing"], default="random")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--outliers", choices=["auto"], default=None,
                        help="create the session with outliers=auto (streamed rejection)")
    parser.add_argument("--dump-latencies", metavar="PREFIX",
                        help="write each update's latency (ms, one per line, in stream order) to "
                             "PREFIX-<robots>.txt")
    args = parser.parse_args()
    path = args.data_dir / args.dataset
    graph = g2o.load(path)
    clean_chi2, clean_positions, optimum = clean_optimum(args.factord, path)
    for robots in args.robots:
        print(json.dumps(run_split(args, graph, robots, clean_chi2, clean_positions, optimum)),
              flush=True)


if __name__ == "__main__":
    main()
