#!/usr/bin/env python3
"""Scores a robust solve against the clean optimum (issue 54's benchmark).

    python3 evaluate.py --clean CLEAN_OPT.g2o --solved SOLVED.g2o --truth WRONG.truth \
        [--rejected-lines 12,40,...]

Prints one JSON object: position RMSE after rigid alignment (2D: closed form; 3D: Horn's
quaternion method) of SOLVED's poses onto CLEAN_OPT's, and the rejection precision and recall
(rejected edges identified by their line numbers in the corrupted input, as the truth file
lists them). Standard library only.
"""
import argparse
import json
import math


def positions(path):
    out = {}
    for line in open(path):
        f = line.split()
        if f and f[0] == "VERTEX_SE2":
            out[int(f[1])] = (float(f[2]), float(f[3]), 0.0)
        elif f and f[0] == "VERTEX_SE3:QUAT":
            out[int(f[1])] = (float(f[2]), float(f[3]), float(f[4]))
    return out


def mean(points):
    n = len(points)
    return tuple(sum(p[k] for p in points) / n for k in range(3))


def jacobi_eigen(a):
    """Eigen-decomposition of a symmetric 4x4 matrix (cyclic Jacobi); (values, columns)."""
    n = 4
    a = [row[:] for row in a]
    v = [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]
    for _ in range(100):
        off = sum(a[i][j] ** 2 for i in range(n) for j in range(n) if i != j)
        if off < 1e-30:
            break
        for p in range(n):
            for q in range(p + 1, n):
                if abs(a[p][q]) < 1e-300:
                    continue
                theta = (a[q][q] - a[p][p]) / (2 * a[p][q])
                t = math.copysign(1.0, theta) / (abs(theta) + math.sqrt(theta * theta + 1))
                c = 1 / math.sqrt(t * t + 1)
                s = t * c
                for k in range(n):
                    akp, akq = a[k][p], a[k][q]
                    a[k][p], a[k][q] = c * akp - s * akq, s * akp + c * akq
                for k in range(n):
                    apk, aqk = a[p][k], a[q][k]
                    a[p][k], a[q][k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = v[k][p], v[k][q]
                    v[k][p], v[k][q] = c * vkp - s * vkq, s * vkp + c * vkq
    return [a[i][i] for i in range(n)], v


def rotate(q, p):
    w, x, y, z = q
    r = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return tuple(sum(r[i][k] * p[k] for k in range(3)) for i in range(3))


def aligned_rmse(reference, estimate):
    keys = sorted(set(reference) & set(estimate))
    a = [estimate[k] for k in keys]
    b = [reference[k] for k in keys]
    ca, cb = mean(a), mean(b)
    a = [tuple(p[i] - ca[i] for i in range(3)) for p in a]
    b = [tuple(p[i] - cb[i] for i in range(3)) for p in b]
    s = [[sum(p[i] * q[j] for p, q in zip(a, b)) for j in range(3)] for i in range(3)]
    sxx, sxy, sxz = s[0]
    syx, syy, syz = s[1]
    szx, szy, szz = s[2]
    n = [[sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
         [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
         [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
         [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz]]
    values, vectors = jacobi_eigen(n)
    best = max(range(4), key=lambda i: values[i])
    q = tuple(vectors[k][best] for k in range(4))
    total = 0.0
    for p, r in zip(a, b):
        m = rotate(q, p)
        total += sum((m[i] - r[i]) ** 2 for i in range(3))
    return math.sqrt(total / len(keys))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clean", required=True)
    p.add_argument("--solved", required=True)
    p.add_argument("--truth", required=True)
    p.add_argument("--rejected-lines", default="")
    a = p.parse_args()
    wrong = {int(line.split()[0]) for line in open(a.truth) if line.strip()}
    rejected = {int(x) for x in a.rejected_lines.split(",") if x}
    tp = len(wrong & rejected)
    result = {
        "rmse_m": aligned_rmse(positions(a.clean), positions(a.solved)),
        "wrong": len(wrong),
        "rejected": len(rejected),
        "true_rejections": tp,
        "precision": tp / len(rejected) if rejected else 1.0,
        "recall": tp / len(wrong) if wrong else 1.0,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
