#!/usr/bin/env python3
"""Large 3D pose graphs with loop closures: a Manhattan world of several storeys (a parking
garage, a multi-level warehouse), for streaming 3D maps beyond sphere2500's 2 500 poses.

    garage_gen.py --poses 20000 [--seed 1] [--out FILE] [--floors 4] [--side M] [--block 4]
                  [--storey 3.0] [--ramp-probability 0.1] [--sigma-t 0.02] [--sigma-r 0.01]
                  [--closure-radius 2.0] [--closure-probability 0.03] [--max-closures 5]

Writes a g2o file (VERTEX_SE3:QUAT + EDGE_SE3:QUAT with the full 6x6 information, upper
triangle) and prints one JSON line describing it. Default output:
~/.cache/factord/data/garage_<poses>_s<seed>.g2o (never into the repository). Deterministic as
manhattan_gen.py is: numpy's PCG64 seeded with --seed, draws in a fixed order, numbers printed
with %.9g; the JSON line includes the sha256.

The world: each floor is manhattan_gen.py's street grid (intersections every --block metres,
1 m per pose, the same turn frequencies at intersections), floors --storey metres apart. At an
intersection the robot takes, with --ramp-probability, a ramp to the floor above or below (if
there is one): the next street segment climbs or descends one storey over its --block poses,
pitched along the street. The true orientation is the heading (yaw) and, on a ramp, the pitch,
so rotations are genuinely 3D. The side defaults so that each floor has M3500's area per pose
(about 1.5 m^2) for its share of the poses: the map grows with the stream.

Loop closures as in manhattan_gen.py, with 3D distances: at pose i every earlier pose
j <= i - 4 within --closure-radius is a candidate, each kept with --closure-probability, at most
--max-closures per pose (nearest first).

Noise: every measurement is the true relative pose Z = Xi^-1 Xj perturbed as Z Exp([dt; dr])
with dt ~ N(0, sigma_t^2 I) (translation, m) and dr ~ N(0, sigma_r^2 I) (rotation, rad). The
information matrix is g2o's for that noise: diag(1/sigma_t^2 (x3), 4/sigma_r^2 (x3)), the
rotation part for g2o's error, the quaternion's vector part, which is about half the angle.

Vertex values: the composition of the noisy odometry (as in manhattan_gen.py's default); the
streaming benchmarks predict each pose from its odometry edge anyway.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys

import numpy as np

from manhattan_gen import M3500_AREA_PER_POSE, MIN_GAP, TURN_P, add_closure_args, draw_closures

# manhattan_gen.py's turns at an intersection (straight, left, right, back) in quarter turns.
TURN_STEPS = (0, 1, 3, 2)
HEADINGS = ((1, 0), (0, 1), (-1, 0), (0, -1))


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--poses", type=int, required=True)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out")
    p.add_argument("--floors", type=int, default=4)
    p.add_argument("--side", type=float, help="floor side in metres (default: M3500's area per pose)")
    p.add_argument("--block", type=int, default=4)
    p.add_argument("--storey", type=float, default=3.0)
    p.add_argument("--ramp-probability", type=float, default=0.1)
    p.add_argument("--sigma-t", type=float, default=0.02)
    p.add_argument("--sigma-r", type=float, default=0.01)
    add_closure_args(p)
    a = p.parse_args()
    if a.poses < 2 or a.floors < 1 or a.block < 1:
        p.error("--poses must be >= 2, --floors and --block >= 1")
    return a


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(angle) / angle * k + (1 - math.cos(angle)) / angle**2 * (k @ k)


def quaternion(r: np.ndarray) -> tuple:
    """(qx, qy, qz, qw) of a rotation matrix, qw >= 0 (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = s / 4
        v[j] = (r[j, i] + r[i, j]) / s
        v[k] = (r[k, i] + r[i, k]) / s
        q = (v[0], v[1], v[2], (r[k, j] - r[j, k]) / s)
    return q if q[3] >= 0 else tuple(-c for c in q)


def walk(a: argparse.Namespace, side: int, rng: np.random.Generator):
    """The true trajectory: per pose (x, y, floor level z in storeys as a float, heading index,
    climb per pose in storeys: 0 on a floor, +-1/block on a ramp)."""
    x, y, h, level, climb = 0, 0, 0, 0.0, 0.0
    half = side // 2
    poses = [(x, y, level, h, climb)]
    for _ in range(1, a.poses):
        if x % a.block == 0 and y % a.block == 0:
            level = round(level)
            ok = []
            for steps in TURN_STEPS:
                nh = (h + steps) % 4
                nx, ny = x + HEADINGS[nh][0], y + HEADINGS[nh][1]
                ok.append(abs(nx) <= half and abs(ny) <= half)
            p = TURN_P * np.array(ok, dtype=float)
            h = (h + TURN_STEPS[int(rng.choice(4, p=p / p.sum()))]) % 4
            climb = 0.0
            if rng.random() < a.ramp_probability:
                ways = [d for d in (-1, 1) if 0 <= level + d < a.floors]
                if ways:
                    climb = ways[int(rng.integers(len(ways)))] / a.block
        x, y, level = x + HEADINGS[h][0], y + HEADINGS[h][1], level + climb
        poses.append((x, y, level, h, climb))
    return poses


def main() -> int:
    a = parse_args()
    rng = np.random.default_rng(a.seed)
    side = a.side if a.side is not None else math.sqrt(M3500_AREA_PER_POSE * a.poses / a.floors)
    side = max(2 * a.block, a.block * 2 * round(side / (2 * a.block)))
    grid = walk(a, int(side), rng)
    truth = []
    for x, y, level, h, climb in grid:
        pitch = -math.atan2(climb * a.storey, 1.0)  # nose up on the way up
        r = rot_z(h * math.pi / 2) @ rot_y(pitch)
        truth.append((r, np.array([float(x), float(y), level * a.storey])))
    st, sr = a.sigma_t, a.sigma_r
    diagonal = [1 / st**2] * 3 + [4 / sr**2] * 3
    info = " ".join(f"{diagonal[r]:.9g}" if c == r else "0" for r in range(6) for c in range(r, 6))

    def measure(i, j):
        (ri, ti), (rj, tj) = truth[i], truth[j]
        rz, tz = ri.T @ rj, ri.T @ (tj - ti)
        dt, dr = st * rng.standard_normal(3), sr * rng.standard_normal(3)
        return rz @ exp_so3(dr), tz + rz @ dt

    cells: dict = {}
    radius = a.closure_radius
    reach = int(math.ceil(radius))
    edges, guess = [], [truth[0]]
    closures_per_pose = np.zeros(a.poses, dtype=np.int64)
    cell_of = [(x, y, round(level * a.storey)) for x, y, level, _, _ in grid]
    for i in range(1, a.poses):
        z = measure(i - 1, i)
        edges.append((i - 1, i, z))
        rg, tg = guess[-1]
        guess.append((rg @ z[0], tg + rg @ z[1]))
        if i - MIN_GAP >= 0:
            cells.setdefault(cell_of[i - MIN_GAP], []).append(i - MIN_GAP)
        cx, cy, cz = cell_of[i]
        near = []
        for dx in range(-reach, reach + 1):
            for dy in range(-reach, reach + 1):
                for dz in range(-reach, reach + 1):
                    for j in cells.get((cx + dx, cy + dy, cz + dz), ()):
                        d = float(np.linalg.norm(truth[j][1] - truth[i][1]))
                        if d <= radius:
                            near.append((d, j))
        kept = draw_closures(near, a, rng)
        edges.extend((j, i, measure(j, i)) for j in kept)
        closures_per_pose[i] = len(kept)

    def pose_text(r, t):
        q = quaternion(r)
        return " ".join(f"{v:.9g}" for v in (*t, *q))

    out = a.out or os.path.expanduser(f"~/.cache/factord/data/garage_{a.poses}_s{a.seed}.g2o")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    lines = [f"VERTEX_SE3:QUAT {k} {pose_text(*p)}\n" for k, p in enumerate(guess)]
    lines += [f"EDGE_SE3:QUAT {i} {j} {pose_text(*z)} {info}\n" for i, j, z in edges]
    text = "".join(lines)
    with open(out, "w") as fh:
        fh.write(text)
    print(json.dumps({
        "file": out, "poses": a.poses, "edges": len(edges), "loop_closures": len(edges) - (a.poses - 1),
        "closures_per_pose": (len(edges) - (a.poses - 1)) / a.poses,
        "closures_per_pose_histogram": np.bincount(closures_per_pose).tolist(),
        "side_m": side, "floors": a.floors, "floors_visited": len({round(g[2]) for g in grid}),
        "distinct_cells": len(set(cell_of)), "seed": a.seed,
        "sha256": hashlib.sha256(text.encode()).hexdigest(),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
