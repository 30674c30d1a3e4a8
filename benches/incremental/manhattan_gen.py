#!/usr/bin/env python3
"""Large Manhattan-world 2D pose graphs with loop closures, in the style of Olson's M3500.

    manhattan_gen.py --poses 100000 [--seed 1] [--out FILE] [--values odometry|truth]
                     [--side M] [--block 4] [--sigma-xy 0.02] [--sigma-theta 0.02]
                     [--closure-radius 2.0] [--closure-probability 0.03] [--max-closures 5]

Writes a g2o file (VERTEX_SE2 + EDGE_SE2 with the full 3x3 information, upper triangle, g2o
order) and prints one JSON line describing it. Default output:
~/.cache/factord/data/manhattan_<poses>_s<seed>.g2o (never into the repository). Deterministic:
numpy's PCG64 seeded with --seed, every draw made in a fixed order, numbers printed with %.9g,
so the same arguments give the same bytes on any machine (the JSON line includes the sha256).

The world (measured on input_M3500_g2o's optimum, see benches/history/issue-16-incremental-engine.md,
"Issue 16 acceptance harness"): streets on a square grid with intersections every --block (4) metres; the robot
moves 1 m per pose along a street; at an intersection it goes straight with probability 0.05,
turns left or right with 0.31 each and turns back with 0.33 (M3500: 5 %, 31 %, 31 %, 32 %),
never leaving the square world of side --side metres. The odometry of a step that turns by t is
(cos t, sin t, t): turn, then 1 m along the new heading, as in M3500. The default side grows
with the graph so that the area per pose is M3500's (about 1.5 m^2): 72 m at 3 500 poses,
120 m at 10 000, 384 m at 100 000; the map grows with the stream, as a robot exploring a city.

Loop closures: at pose i, every earlier pose j <= i - 4 whose true position is within
--closure-radius (2 m) is a candidate, and each is kept with --closure-probability, at most
--max-closures per pose (the nearest kept first). M3500: 0.56 closures per pose, distances
mostly 0-2 m, gaps from 4 poses up. Closure measurements are the true relative pose plus noise.

Noise: every measurement (odometry and closures) is the true relative pose (x, y, theta) plus
independent N(0, sigma^2) on x, y (--sigma-xy, 0.02 m) and theta (--sigma-theta, 0.02 rad)
(M3500's odometry residuals: about 0.022 m and 0.023 rad), and its information is the true
inverse covariance diag(1/sx^2, 1/sx^2, 1/st^2), so the optimum's chi2 is about the number of
residual degrees of freedom minus those of the poses.

Vertex values (--values): 'odometry' (default, as in M3500: pose k is the composition of the
noisy odometry up to k, so the initial guess drifts) or 'truth' (the ground truth, for
debugging). The streaming benchmarks ignore the values of poses with an odometry edge (they
are predicted from it), so the choice matters only for batch solves from the file.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys

import numpy as np

M3500_AREA_PER_POSE = 1.5  # m^2 (about 90 m x 58 m for 3 500 poses)
MIN_GAP = 4  # M3500's smallest loop-closure gap
# At an intersection: straight, left, right, back (M3500's frequencies).
TURNS = np.array([0.0, math.pi / 2, -math.pi / 2, math.pi])
TURN_P = np.array([0.05, 0.31, 0.31, 0.33])


def add_closure_args(p: argparse.ArgumentParser) -> None:
    """The loop-closure options, shared with garage_gen.py."""
    p.add_argument("--closure-radius", type=float, default=2.0)
    p.add_argument("--closure-probability", type=float, default=0.03)
    p.add_argument("--max-closures", type=int, default=5)


def draw_closures(near: list, a: argparse.Namespace, rng: np.random.Generator) -> list:
    """The loop closures kept among the candidates `near`, (distance, earlier pose) pairs: each
    with --closure-probability, at most --max-closures, the nearest first; in pose order. Draws
    nothing when there is no candidate (so the stream of draws is the same as it always was)."""
    if not near:
        return []
    near.sort()
    keep = rng.random(len(near)) < a.closure_probability
    return sorted([j for (_, j), k in zip(near, keep) if k][: a.max_closures])


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--poses", type=int, required=True)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out")
    p.add_argument("--values", choices=["odometry", "truth"], default="odometry")
    p.add_argument("--side", type=float, help="world side in metres (default: M3500's area per pose)")
    p.add_argument("--block", type=int, default=4)
    p.add_argument("--sigma-xy", type=float, default=0.02)
    p.add_argument("--sigma-theta", type=float, default=0.02)
    add_closure_args(p)
    a = p.parse_args()
    if a.poses < 2:
        p.error("--poses must be >= 2")
    return a


def compose(a, b):
    """SE(2) composition a * b of (x, y, theta) tuples."""
    c, s = math.cos(a[2]), math.sin(a[2])
    th = a[2] + b[2]
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], math.atan2(math.sin(th), math.cos(th)))


def between(a, b):
    """a^-1 * b."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    th = b[2] - a[2]
    return (c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(th), math.cos(th)))


def walk(n: int, side: int, block: int, rng: np.random.Generator):
    """Integer grid positions and headings (multiples of pi/2) of the true trajectory."""
    headings = [(1, 0), (0, 1), (-1, 0), (0, -1)]
    x, y, h = 0, 0, 0
    poses = [(x, y, h)]
    half = side // 2
    turn_index = {0.0: 0, math.pi / 2: 1, -math.pi / 2: 3, math.pi: 2}
    for _ in range(1, n):
        if x % block == 0 and y % block == 0:
            # Draw among the turns that stay inside the world (renormalised).
            ok = []
            for t in TURNS:
                nh = (h + turn_index[float(t)]) % 4
                nx, ny = x + headings[nh][0], y + headings[nh][1]
                ok.append(abs(nx) <= half and abs(ny) <= half)
            p = TURN_P * np.array(ok, dtype=float)
            k = int(rng.choice(4, p=p / p.sum()))
            h = (h + turn_index[float(TURNS[k])]) % 4
        x, y = x + headings[h][0], y + headings[h][1]
        poses.append((x, y, h))
    return poses


def main() -> int:
    a = parse_args()
    rng = np.random.default_rng(a.seed)
    side = a.side if a.side is not None else math.sqrt(M3500_AREA_PER_POSE * a.poses)
    side = max(2 * a.block, a.block * 2 * round(side / (2 * a.block)))
    grid = walk(a.poses, int(side), a.block, rng)
    truth = [(float(x), float(y), math.atan2(math.sin(h * math.pi / 2), math.cos(h * math.pi / 2)))
             for x, y, h in grid]
    sx, st = a.sigma_xy, a.sigma_theta
    info = f"{1 / sx**2:.9g} 0 0 {1 / sx**2:.9g} 0 {1 / st**2:.9g}"

    def measure(i, j):
        z = between(truth[i], truth[j])
        n = rng.standard_normal(3)
        return (z[0] + sx * n[0], z[1] + sx * n[1], z[2] + st * n[2])

    cells: dict = {}
    r = a.closure_radius
    reach = int(math.ceil(r))
    edges = []
    guess = [truth[0]]
    closures_per_pose = np.zeros(a.poses, dtype=np.int64)
    for i in range(1, a.poses):
        z = measure(i - 1, i)
        edges.append((i - 1, i, z))
        guess.append(compose(guess[-1], z))
        if i - MIN_GAP >= 0:
            gx, gy, _ = grid[i - MIN_GAP]
            cells.setdefault((gx, gy), []).append(i - MIN_GAP)
        x, y, _ = grid[i]
        near = []
        for dx in range(-reach, reach + 1):
            for dy in range(-reach, reach + 1):
                d = math.hypot(dx, dy)
                if d <= r:
                    near.extend((d, j) for j in cells.get((x + dx, y + dy), ()))
        kept = draw_closures(near, a, rng)
        edges.extend((j, i, measure(j, i)) for j in kept)
        closures_per_pose[i] = len(kept)
    values = guess if a.values == "odometry" else truth

    out = a.out or os.path.expanduser(f"~/.cache/factord/data/manhattan_{a.poses}_s{a.seed}.g2o")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    lines = [f"VERTEX_SE2 {k} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}\n" for k, p in enumerate(values)]
    lines += [f"EDGE_SE2 {i} {j} {z[0]:.9g} {z[1]:.9g} {z[2]:.9g} {info}\n" for i, j, z in edges]
    text = "".join(lines)
    with open(out, "w") as fh:
        fh.write(text)
    hist = np.bincount(closures_per_pose).tolist()
    print(json.dumps({
        "file": out, "poses": a.poses, "edges": len(edges), "loop_closures": len(edges) - (a.poses - 1),
        "closures_per_pose": (len(edges) - (a.poses - 1)) / a.poses, "closures_per_pose_histogram": hist,
        "side_m": side, "distinct_cells": len(set((x, y) for x, y, _ in grid)), "seed": a.seed,
        "values": a.values, "sha256": hashlib.sha256(text.encode()).hexdigest(),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
