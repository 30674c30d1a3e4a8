#!/usr/bin/env python3
"""A synthetic BAL problem of any size, written in BAL's text format (standard library only).

    synthetic.py CAMERAS POINTS [--views 6] [--band 0] [--seed 7] [-o FILE]

The model of `tests/api/job_budget_ba.rs::synthetic_bal`: cameras about 20 units from a Gaussian
cloud of points (σ 3), focal 500 ± 10, no distortion; each point seen by `views` distinct
cameras drawn at random (so nearly every camera pair shares a point and the reduced camera
system is nearly dense); one pixel of Gaussian noise on every observation; the cameras'
rotation and translation (σ 0.01) and the points (σ 0.05) perturbed so the solve has work to
do. `--band B` (B ≥ views) draws each point's cameras from B consecutive ones instead, as a
camera moving along a path sees a point from neighbouring frames only: the reduced camera system
is then banded and stays sparse (the sparse explicit Schur path). The same arguments give the
same bytes. Memory and time comparisons with Ceres use it
(`benches/history/issue-57-ba.md`): 1000 cameras / 300 000 points / 6 views is issue 57's
"synthetic 1 000 cameras" problem.
"""
import argparse
import math
import random
import sys


def rotate(aa, x):
    """Rodrigues: the angle-axis rotation `aa` applied to `x` (as Ceres' AngleAxisRotatePoint)."""
    theta = math.sqrt(aa[0] ** 2 + aa[1] ** 2 + aa[2] ** 2)
    if theta < 1e-12:
        c = (aa[1] * x[2] - aa[2] * x[1], aa[2] * x[0] - aa[0] * x[2], aa[0] * x[1] - aa[1] * x[0])
        return [x[i] + c[i] for i in range(3)]
    w = [a / theta for a in aa]
    cos, sin = math.cos(theta), math.sin(theta)
    c = (w[1] * x[2] - w[2] * x[1], w[2] * x[0] - w[0] * x[2], w[0] * x[1] - w[1] * x[0])
    d = (w[0] * x[0] + w[1] * x[1] + w[2] * x[2]) * (1 - cos)
    return [x[i] * cos + c[i] * sin + w[i] * d for i in range(3)]


def project(camera, x):
    p = rotate(camera[0:3], x)
    p = [p[i] + camera[3 + i] for i in range(3)]
    px, py = -p[0] / p[2], -p[1] / p[2]
    n = px * px + py * py
    r = 1.0 + camera[7] * n + camera[8] * n * n
    return camera[6] * r * px, camera[6] * r * py


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cameras", type=int)
    ap.add_argument("points", type=int)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--band", type=int, default=0,
                    help="draw each point's cameras from this many consecutive ones (0: from all)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("-o", "--output", default="-")
    args = ap.parse_args()
    if args.views > args.cameras:
        sys.exit("--views cannot exceed the number of cameras")
    if args.band and not args.views <= args.band <= args.cameras:
        sys.exit("--band must lie between --views and the number of cameras")
    rng = random.Random(args.seed)
    g = rng.gauss
    truth = [[0.1 * g(0, 1), 0.1 * g(0, 1), 0.1 * g(0, 1), g(0, 1), g(0, 1), -20.0 + g(0, 1),
              500.0 + 10.0 * g(0, 1), 0.0, 0.0] for _ in range(args.cameras)]
    out = sys.stdout if args.output == "-" else open(args.output, "w")
    write = out.write
    write(f"{args.cameras} {args.points} {args.points * args.views}\n")
    guesses = []
    for j in range(args.points):
        x = [3.0 * g(0, 1), 3.0 * g(0, 1), 3.0 * g(0, 1)]
        guesses.append([x[i] + 0.05 * g(0, 1) for i in range(3)])
        if args.band:
            first = rng.randrange(args.cameras - args.band + 1)
            seen = sorted(rng.sample(range(first, first + args.band), args.views))
        else:
            seen = sorted(rng.sample(range(args.cameras), args.views))
        lines = []
        for i in seen:
            u, v = project(truth[i], x)
            lines.append(f"{i} {j} {u + g(0, 1):.4f} {v + g(0, 1):.4f}\n")
        write("".join(lines))
    for camera in truth:
        guess = [c + 0.01 * g(0, 1) if k < 6 else c for k, c in enumerate(camera)]
        write("".join(f"{v:e}\n" for v in guess))
    for p in guesses:
        write(f"{p[0]:e}\n{p[1]:e}\n{p[2]:e}\n")
    if out is not sys.stdout:
        out.close()


if __name__ == "__main__":
    main()
