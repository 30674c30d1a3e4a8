"""Minimal pose-graph reader shared by the reference drivers (gtsam_solve.py, g2o_solve.py).

Both drivers build their problem from the *same* parsed data, so GTSAM and g2o see exactly the
same vertices, measurements and information matrices (no library loader is involved).

Supported records (see /work/shared/data/MANIFEST.md):

  2D, g2o   VERTEX_SE2 id x y theta
            EDGE_SE2   i j dx dy dtheta  I11 I12 I13 I22 I23 I33          (upper triangle, row-major)
  2D, TORO  VERTEX2    id x y theta
            EDGE2      i j dx dy dtheta  Ixx Ixy Iyy Itt Ixt Iyt          (TORO order!)
  3D, g2o   VERTEX_SE3:QUAT id x y z qx qy qz qw
            EDGE_SE3:QUAT   i j x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66   (21 numbers, order (t, R))

The measurement z of an edge "i j z" is X_i^-1 X_j.  The information order of 2D edges is decided
by the record tag (EDGE_SE2 -> g2o order, EDGE2 -> TORO order) unless `info_order` forces one.
`EQUIV` lines (TORO node merges) are ignored and counted.  Vertices and edges may come from two
files (the course's `<name>-v.dat` / `<name>-e.dat`).

This module depends only on the standard library; `chi2_g2o_convention` imports numpy lazily.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

Matrix = List[List[float]]


@dataclass
class Edge:
    i: int
    j: int
    # 2D: (dx, dy, dtheta); 3D: (x, y, z, qx, qy, qz, qw) with a unit quaternion
    measurement: Tuple[float, ...]
    # 3x3 (x, y, theta) or 6x6 (tx, ty, tz, rx, ry, rz) information matrix, file order
    information: Matrix


@dataclass
class PoseGraph:
    dim: int  # 2 or 3
    # 2D: id -> (x, y, theta); 3D: id -> (x, y, z, qx, qy, qz, qw), unit quaternion
    vertices: Dict[int, Tuple[float, ...]] = field(default_factory=dict)
    edges: List[Edge] = field(default_factory=list)
    ignored_equiv: int = 0

    @property
    def first_vertex(self) -> int:
        """The gauge vertex: lowest id."""
        return min(self.vertices)


def _sym_from_upper(vals: Sequence[float], n: int) -> Matrix:
    """Symmetric n x n matrix from a row-major upper triangle."""
    m = [[0.0] * n for _ in range(n)]
    k = 0
    for r in range(n):
        for c in range(r, n):
            m[r][c] = m[c][r] = vals[k]
            k += 1
    return m


def _info_toro(v: Sequence[float]) -> Matrix:
    xx, xy, yy, tt, xt, yt = v
    return [[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]]


def _unit_quat(qx: float, qy: float, qz: float, qw: float) -> Tuple[float, float, float, float]:
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    return qx / n, qy / n, qz / n, qw / n


def read_pose_graph(path: str, edges_path: Optional[str] = None, info_order: str = "auto") -> PoseGraph:
    """Parse a pose graph.  info_order: 'auto' (by tag), 'g2o' or 'toro' (forced for 2D edges)."""
    if info_order not in ("auto", "g2o", "toro"):
        raise ValueError(f"unknown information order {info_order!r}")
    dims = set()
    vertices: Dict[int, Tuple[float, ...]] = {}
    edges: List[Edge] = []
    equiv = 0
    for fname in [path] + ([edges_path] if edges_path else []):
        with open(fname, "r") as fh:
            for lineno, line in enumerate(fh, 1):
                tok = line.split()
                if not tok or tok[0].startswith("#"):
                    continue
                tag = tok[0]
                try:
                    if tag in ("VERTEX_SE2", "VERTEX2"):
                        dims.add(2)
                        vertices[int(tok[1])] = tuple(float(t) for t in tok[2:5])
                    elif tag in ("EDGE_SE2", "EDGE2"):
                        dims.add(2)
                        vals = [float(t) for t in tok[3:12]]
                        order = info_order if info_order != "auto" else ("g2o" if tag == "EDGE_SE2" else "toro")
                        info = _sym_from_upper(vals[3:9], 3) if order == "g2o" else _info_toro(vals[3:9])
                        edges.append(Edge(int(tok[1]), int(tok[2]), tuple(vals[0:3]), info))
                    elif tag == "VERTEX_SE3:QUAT":
                        dims.add(3)
                        v = [float(t) for t in tok[2:9]]
                        vertices[int(tok[1])] = tuple(v[0:3]) + _unit_quat(*v[3:7])
                    elif tag == "EDGE_SE3:QUAT":
                        dims.add(3)
                        v = [float(t) for t in tok[3:31]]
                        if len(v) != 28:
                            raise ValueError("expected 28 numbers")
                        meas = tuple(v[0:3]) + _unit_quat(*v[3:7])
                        edges.append(Edge(int(tok[1]), int(tok[2]), meas, _sym_from_upper(v[7:28], 6)))
                    elif tag == "EQUIV":
                        equiv += 1
                    else:
                        raise ValueError(f"unsupported record {tag!r}")
                except (ValueError, IndexError) as exc:
                    raise ValueError(f"{fname}:{lineno}: {exc}") from exc
    if len(dims) != 1:
        raise ValueError(f"{path}: expected one pose dimension, found {sorted(dims) or 'none'}")
    if not vertices:
        raise ValueError(f"{path}: no vertices (edges-only files need an initialisation; not supported)")
    for e in edges:
        if e.i not in vertices or e.j not in vertices:
            raise ValueError(f"{path}: edge {e.i}-{e.j} references an unknown vertex")
    return PoseGraph(dims.pop(), vertices, edges, equiv)


# --------------------------------------------------------------------------------------------
# chi2 in g2o's convention, evaluated independently of any library (numpy).
#   2D: e = t2v(Z^-1 Xi^-1 Xj), angle wrapped to (-pi, pi]
#   3D: e = [t; qvec] of Z^-1 Xi^-1 Xj with the error quaternion normalised to w >= 0
#   chi2 = sum e^T Omega e  (no 1/2)
# --------------------------------------------------------------------------------------------

def _quat_mul(a, b):
    """Hamilton product of (..., 4) arrays in (x, y, z, w) order."""
    import numpy as np

    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], axis=-1)


def _quat_rotate(q, v):
    """Rotate (..., 3) vectors v by unit quaternions q (x, y, z, w)."""
    import numpy as np

    qv = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(qv, v)
    return v + w * t + np.cross(qv, t)


def chi2_g2o_convention(graph: PoseGraph, poses: Dict[int, Sequence[float]]) -> float:
    """sum e^T Omega e over all edges of `graph` at `poses` (same layout as graph.vertices)."""
    import numpy as np

    ii = [e.i for e in graph.edges]
    jj = [e.j for e in graph.edges]
    Z = np.array([e.measurement for e in graph.edges], dtype=float)
    Om = np.array([e.information for e in graph.edges], dtype=float)
    Xi = np.array([poses[k] for k in ii], dtype=float)
    Xj = np.array([poses[k] for k in jj], dtype=float)
    if graph.dim == 2:
        def rot_T(th, v):  # R(th)^T v
            c, s = np.cos(th), np.sin(th)
            return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], axis=1)
        dij = rot_T(Xi[:, 2], Xj[:, :2] - Xi[:, :2])          # Xi^-1 Xj translation
        tij = Xj[:, 2] - Xi[:, 2]
        et = rot_T(Z[:, 2], dij - Z[:, :2])
        eth = np.arctan2(np.sin(tij - Z[:, 2]), np.cos(tij - Z[:, 2]))
        err = np.column_stack([et, eth])
    else:
        conj = np.array([-1.0, -1.0, -1.0, 1.0])
        qi, qj, qz = Xi[:, 3:], Xj[:, 3:], Z[:, 3:]
        dij = _quat_rotate(qi * conj, Xj[:, :3] - Xi[:, :3])
        et = _quat_rotate(qz * conj, dij - Z[:, :3])
        qe = _quat_mul(qz * conj, _quat_mul(qi * conj, qj))
        qe /= np.linalg.norm(qe, axis=1, keepdims=True)
        qe *= np.where(qe[:, 3:4] < 0, -1.0, 1.0)
        err = np.column_stack([et, qe[:, :3]])
    return float(np.einsum("ni,nij,nj->", err, Om, err))
