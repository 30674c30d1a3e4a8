#!/usr/bin/env python3
"""Wrong loop closures added to a g2o pose graph, with a fixed seed (issue 54's benchmark).

    python3 generate.py --input FILE --fraction 0.2 --kind random|aliasing --seed 54 \
        --out OUT.g2o --truth OUT.truth

The output is the input unchanged followed by the wrong closures (EDGE_SE2 or EDGE_SE3:QUAT, each
with the information of a randomly chosen genuine loop closure, so none is weaker than a real one).
Their number is round(fraction x the loop closures already in the file), where a loop closure is
an edge whose two ids differ by something other than 1.

  random    uniform pose pairs (ids at least 2 apart), uniform measurements: translation in a box
            of +-10 m per axis, rotation uniform (2D: angle in [-pi, pi); 3D: uniform quaternion).
  aliasing  groups of 5-20 consecutive closures (i0+k, j0+k) that agree with each other but not
            with the map: segment j0.. is laid over segment i0.. with one wrong relative transform
            A, z_k = (x_{i0+k}^-1 x_{i0}) A (x_{j0}^-1 x_{j0+k}) from the file's vertex estimates
            (exact for the odometry-composed initial guess), i.e. a place seen twice.

The truth file lists one wrong edge a line: `<line number in OUT> <id_i> <id_j>`. Standard library
only, so it runs with any python3.
"""
import argparse
import math
import random


# --- SE(2) -----------------------------------------------------------------------------------
def se2_compose(a, b):
    x, y, t = a
    c, s = math.cos(t), math.sin(t)
    return (x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], wrap(t + b[2]))


def se2_inverse(a):
    x, y, t = a
    c, s = math.cos(t), math.sin(t)
    return (-(c * x + s * y), -(-s * x + c * y), -t)


def wrap(t):
    return (t + math.pi) % (2 * math.pi) - math.pi


# --- SE(3): (t, q) with q = (x, y, z, w) -------------------------------------------------------
def q_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def q_conj(q):
    return (-q[0], -q[1], -q[2], q[3])


def q_rotate(q, v):
    p = q_mul(q_mul(q, (v[0], v[1], v[2], 0.0)), q_conj(q))
    return p[:3]


def se3_compose(a, b):
    t = q_rotate(a[1], b[0])
    return ((a[0][0] + t[0], a[0][1] + t[1], a[0][2] + t[2]), q_mul(a[1], b[1]))


def se3_inverse(a):
    qi = q_conj(a[1])
    t = q_rotate(qi, a[0])
    return ((-t[0], -t[1], -t[2]), qi)


def random_quaternion(rng):
    # Shoemake's uniform rotation.
    u1, u2, u3 = rng.random(), rng.random(), rng.random()
    a, b = math.sqrt(1 - u1), math.sqrt(u1)
    return (a * math.sin(2 * math.pi * u2), a * math.cos(2 * math.pi * u2),
            b * math.sin(2 * math.pi * u3), b * math.cos(2 * math.pi * u3))


# --- the file ----------------------------------------------------------------------------------
def read(path):
    lines = open(path).read().splitlines()
    poses, closures_info, dim, ids = {}, [], None, []
    for line in lines:
        f = line.split()
        if not f:
            continue
        if f[0] == "VERTEX_SE2":
            dim = 2
            poses[int(f[1])] = tuple(float(v) for v in f[2:5])
            ids.append(int(f[1]))
        elif f[0] == "VERTEX_SE3:QUAT":
            dim = 3
            v = [float(x) for x in f[2:9]]
            poses[int(f[1])] = (tuple(v[:3]), tuple(v[3:7]))
            ids.append(int(f[1]))
        elif f[0] in ("EDGE_SE2", "EDGE_SE3:QUAT"):
            i, j = int(f[1]), int(f[2])
            if abs(i - j) != 1:
                info = f[6:] if f[0] == "EDGE_SE2" else f[10:]
                closures_info.append(info)
    return lines, poses, sorted(ids), closures_info, dim


def fmt(v):
    return repr(float(v))


def edge(dim, i, j, z, info):
    if dim == 2:
        return "EDGE_SE2 %d %d %s %s %s %s" % (i, j, fmt(z[0]), fmt(z[1]), fmt(z[2]), " ".join(info))
    (t, q) = z
    return "EDGE_SE3:QUAT %d %d %s %s" % (i, j, " ".join(fmt(v) for v in t + q), " ".join(info))


def random_pair(rng, ids):
    while True:
        i, j = rng.choice(ids), rng.choice(ids)
        if abs(i - j) >= 2:
            return min(i, j), max(i, j)


def random_measurement(rng, dim):
    if dim == 2:
        return (rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(-math.pi, math.pi))
    return (tuple(rng.uniform(-10, 10) for _ in range(3)), random_quaternion(rng))


def relative(dim, a, b):
    if dim == 2:
        return se2_compose(se2_inverse(a), b)
    return se3_compose(se3_inverse(a), b)


def compose(dim, a, b):
    return se2_compose(a, b) if dim == 2 else se3_compose(a, b)


def aliasing_groups(rng, dim, poses, ids, count):
    """Groups of consecutive closures, all consistent with one wrong overlay A."""
    out = []
    idset = set(ids)
    while len(out) < count:
        size = min(rng.randint(5, 20), count - len(out))
        i0, j0 = random_pair(rng, ids)
        if j0 - i0 < size + 2:
            continue
        if any((i0 + k) not in idset or (j0 + k) not in idset for k in range(size)):
            continue
        overlay = random_measurement(rng, dim)
        for k in range(size):
            before = relative(dim, poses[i0 + k], poses[i0])
            after = relative(dim, poses[j0], poses[j0 + k])
            out.append((i0 + k, j0 + k, compose(dim, compose(dim, before, overlay), after)))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", required=True)
    p.add_argument("--fraction", type=float, required=True)
    p.add_argument("--kind", choices=["random", "aliasing"], required=True)
    p.add_argument("--seed", type=int, default=54)
    p.add_argument("--out", required=True)
    p.add_argument("--truth", required=True)
    a = p.parse_args()
    rng = random.Random(a.seed)
    lines, poses, ids, closures_info, dim = read(a.input)
    count = round(a.fraction * len(closures_info))
    if a.kind == "random":
        wrong = []
        for _ in range(count):
            i, j = random_pair(rng, ids)
            wrong.append((i, j, random_measurement(rng, dim)))
    else:
        wrong = aliasing_groups(rng, dim, poses, ids, count)
    with open(a.out, "w") as out, open(a.truth, "w") as truth:
        for line in lines:
            out.write(line + "\n")
        number = len(lines)
        for i, j, z in wrong:
            number += 1
            out.write(edge(dim, i, j, z, rng.choice(closures_info)) + "\n")
            truth.write("%d %d %d\n" % (number, i, j))
    print("%s: %d loop closures, %d wrong added (%s, seed %d)" % (a.input, len(closures_info), len(wrong), a.kind, a.seed))


if __name__ == "__main__":
    main()
