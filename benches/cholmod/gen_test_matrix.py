#!/usr/bin/env python3
"""Write SPD test matrices for cholmod_bench in Matrix Market format (one triangle stored).

Stand-in until factord's own H exporter exists. Only the sparsity pattern matters for the
factorisation time, so the values are synthetic but strictly positive definite:

    H = (graph Laplacian + I) ⊗ B,   B = I_b + 0.1·ones(b, b)

  grid:   5-point 2D grid of k×k nodes (block size b; b=1 gives the classic Laplacian + I)
  graph:  the block pattern of a pose graph's normal equations, from a g2o / TORO file's edges
          (b = 3 for 2D, 6 for 3D unless --block is given). Same pattern as J^T J of that graph.

Examples:
  gen_test_matrix.py grid --k 100 --block 1 -o /tmp/grid100.mtx
  gen_test_matrix.py graph --file /work/shared/data/3d/sesync/sphere2500.g2o -o /tmp/sphere2500_H.mtx
"""
import argparse
import sys


def grid_edges(k):
    edges = []
    for i in range(k):
        for j in range(k):
            u = i * k + j
            if i + 1 < k:
                edges.append((u, u + k))
            if j + 1 < k:
                edges.append((u, u + 1))
    return k * k, edges


def graph_edges(path):
    ids, edges, dim = {}, [], None
    with open(path) as f:
        for line in f:
            tok = line.split()
            if not tok:
                continue
            tag = tok[0]
            if tag in ("VERTEX_SE2", "VERTEX2", "VERTEX_SE3:QUAT"):
                ids.setdefault(int(tok[1]), len(ids))
                dim = 3 if tag == "VERTEX_SE3:QUAT" else 2
            elif tag in ("EDGE_SE2", "EDGE2", "EDGE_SE3:QUAT"):
                dim = 3 if tag == "EDGE_SE3:QUAT" else 2
                a, b = int(tok[1]), int(tok[2])
                for v in (a, b):
                    ids.setdefault(v, len(ids))
                edges.append((ids[a], ids[b]))
    if dim is None:
        sys.exit(f"no pose-graph records in {path}")
    return len(ids), edges, dim


def write_mm(path, nodes, edges, b, triangle, comment):
    # accumulate block entries: (I + 0.1·ones) * weight
    diag = [1.0] * nodes                      # the "+ I" term
    off = {}
    for u, v in edges:
        if u == v:
            continue
        diag[u] += 1.0
        diag[v] += 1.0
        key = (min(u, v), max(u, v))
        off[key] = off.get(key, 0.0) - 1.0
    entries = []
    for u in range(nodes):
        for r in range(b):
            for c in range(r, b):
                entries.append((u * b + r, u * b + c, diag[u] * ((r == c) + 0.1)))
    for (u, v), w in off.items():             # u < v: block row u, block column v (upper)
        for r in range(b):
            for c in range(b):
                entries.append((u * b + r, v * b + c, w * ((r == c) + 0.1)))
    if triangle == "lower":
        entries = [(c, r, x) for r, c, x in entries]
    entries.sort(key=lambda e: (e[1], e[0]))  # column-major
    n = nodes * b
    with open(path, "w") as f:
        f.write("%%MatrixMarket matrix coordinate real symmetric\n")
        f.write(f"% {comment}; {triangle} triangle stored\n")
        f.write(f"{n} {n} {len(entries)}\n")
        for r, c, x in entries:
            f.write(f"{r + 1} {c + 1} {x:.17g}\n")
    print(f"{path}: n={n} stored_nnz={len(entries)}", file=sys.stderr)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("kind", choices=["grid", "graph"])
    ap.add_argument("--k", type=int, default=100, help="grid side (grid)")
    ap.add_argument("--file", help="pose-graph file (graph)")
    ap.add_argument("--block", type=int, help="block size (default 1 for grid, 3/6 for 2D/3D graphs)")
    ap.add_argument("--triangle", choices=["upper", "lower"], default="upper")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    if a.kind == "grid":
        nodes, edges = grid_edges(a.k)
        b = a.block or 1
        comment = f"grid {a.k}x{a.k} Laplacian + I, block {b}"
    else:
        if not a.file:
            ap.error("graph needs --file")
        nodes, edges, dim = graph_edges(a.file)
        b = a.block or (6 if dim == 3 else 3)
        comment = f"pose-graph pattern of {a.file}, block {b}"
    write_mm(a.output, nodes, edges, b, a.triangle, comment)


if __name__ == "__main__":
    main()
