"""A small g2o reader (``VERTEX_SE2``, ``EDGE_SE2``, ``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``,
``FIX``) that turns a pose graph into factord's wire form and into the order a robot would stream
it in.

Wire encodings (see the server's ``src/session/catalogue.rs``):

* ``se2`` values and ``between_se2`` measurements: ``[x, y, theta]``; the information is g2o's
  upper triangle (6 numbers, residual order x, y, theta), passed unchanged.
* ``se3`` values and ``between_se3`` measurements: ``[x, y, z, qx, qy, qz, qw]`` (g2o order,
  quaternions normalised here). The information is in factord's residual order (translation, then
  rotation *angle*), while g2o's ``EDGE_SE3:QUAT`` information is defined on ``[t; vec(q)]`` with
  ``vec(q) ~ angle / 2``; it is therefore mapped to ``D Omega D`` with
  ``D = diag(1, 1, 1, 1/2, 1/2, 1/2)`` (21 upper-triangle numbers), as factord's own g2o reader does.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Optional, Set, Tuple, Union

JsonDict = Dict[str, Any]

_ROTATION_SCALE = (1.0, 1.0, 1.0, 0.5, 0.5, 0.5)


@dataclass
class Edge:
    i: int
    j: int
    #: wire measurement ([x, y, theta] or [x, y, z, qx, qy, qz, qw])
    measurement: List[float]
    #: upper triangle, row by row, in factord's residual order (what goes on the wire)
    information: List[float]
    #: upper triangle exactly as in the file (g2o's convention)
    g2o_information: List[float]
    line: int = 0


@dataclass
class Graph:
    #: 2 or 3
    dimension: int
    #: vertex id -> wire value, in file order
    vertices: Dict[int, List[float]] = field(default_factory=dict)
    edges: List[Edge] = field(default_factory=list)
    fixed: Set[int] = field(default_factory=set)

    @property
    def session_kind(self) -> str:
        return "pose_graph_2d" if self.dimension == 2 else "pose_graph_3d"

    @property
    def variable_kind(self) -> str:
        return "se2" if self.dimension == 2 else "se3"

    @property
    def factor_type(self) -> str:
        return "between_se2" if self.dimension == 2 else "between_se3"

    def variable(self, key: int, with_value: bool = True) -> JsonDict:
        """The ``variables[]`` entry of vertex ``key``."""
        spec: JsonDict = {"key": key, "kind": self.variable_kind}
        if with_value:
            spec["value"] = list(self.vertices[key])
        if key in self.fixed:
            spec["fixed"] = True
        return spec

    def factor(self, edge: Edge) -> JsonDict:
        """The ``factors[]`` entry of an edge."""
        return {
            "type": self.factor_type,
            "keys": [edge.i, edge.j],
            "measurement": list(edge.measurement),
            "information": list(edge.information),
        }

    def batches(self, predict: bool = True, limit: Optional[int] = None) -> Iterator[Tuple[int, JsonDict]]:
        """Streaming order: for each vertex id in increasing order, ``(id, batch)`` where the batch
        adds that vertex and every edge whose larger endpoint is that vertex.

        The first vertex carries its value from the file. With ``predict`` (the default), a later
        vertex has no ``value`` when an odometry edge joins it to the previous vertex (by id order):
        the server then predicts it from that edge, which is put first in the batch's factors.
        Without an odometry edge (or with ``predict=False``) the file's value is sent.
        ``limit``: stop after that many vertices.
        """
        by_max: Dict[int, List[Edge]] = {}
        for e in self.edges:
            by_max.setdefault(max(e.i, e.j), []).append(e)
        previous: Optional[int] = None
        for n, key in enumerate(sorted(self.vertices)):
            if limit is not None and n >= limit:
                return
            edges = list(by_max.get(key, []))
            odometry = None
            if previous is not None:
                odometry = next((e for e in edges if {e.i, e.j} == {previous, key}), None)
            omit = predict and odometry is not None
            if odometry is not None:
                edges.remove(odometry)
                edges.insert(0, odometry)
            batch = {
                "variables": [self.variable(key, with_value=not omit)],
                "factors": [self.factor(e) for e in edges],
            }
            yield key, batch
            previous = key

    def subgraph(self, limit: int) -> "Graph":
        """The first ``limit`` vertices (by id) and the edges among them."""
        keep = set(sorted(self.vertices)[:limit])
        return Graph(
            dimension=self.dimension,
            vertices={k: v for k, v in self.vertices.items() if k in keep},
            edges=[e for e in self.edges if e.i in keep and e.j in keep],
            fixed={k for k in self.fixed if k in keep},
        )

    def to_g2o(self) -> str:
        """The graph as g2o text (information in g2o's convention)."""
        vertex = "VERTEX_SE2" if self.dimension == 2 else "VERTEX_SE3:QUAT"
        edge = "EDGE_SE2" if self.dimension == 2 else "EDGE_SE3:QUAT"
        lines = [f"{vertex} {k} " + " ".join(repr(x) for x in v) for k, v in self.vertices.items()]
        lines += [
            f"{edge} {e.i} {e.j} " + " ".join(repr(x) for x in e.measurement + e.g2o_information)
            for e in self.edges
        ]
        if self.fixed:
            lines.append("FIX " + " ".join(str(k) for k in sorted(self.fixed)))
        return "\n".join(lines) + "\n"


def _normalised(q: List[float], where: str) -> List[float]:
    norm = math.sqrt(sum(c * c for c in q))
    if not 0.5 <= norm <= 2.0:
        raise ValueError(f"{where}: quaternion norm {norm} is far from 1")
    return [c / norm for c in q]


def _scale_information_3d(upper: List[float]) -> List[float]:
    out = []
    k = 0
    for r in range(6):
        for c in range(r, 6):
            out.append(upper[k] * _ROTATION_SCALE[r] * _ROTATION_SCALE[c])
            k += 1
    return out


def parse(text: str, name: str = "<g2o>", skip_unknown: bool = False) -> Graph:
    """Parses g2o text. Unknown records raise ``ValueError`` unless ``skip_unknown``."""
    dimension: Optional[int] = None
    vertices: Dict[int, List[float]] = {}
    edges: List[Edge] = []
    fixed: Set[int] = set()

    def dim(d: int, where: str) -> None:
        nonlocal dimension
        if dimension is not None and dimension != d:
            raise ValueError(f"{where}: mixes 2D and 3D records")
        dimension = d

    for number, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{name}:{number}"
        tag = tokens[0]
        expected = {"VERTEX_SE2": 4, "EDGE_SE2": 11, "VERTEX_SE3:QUAT": 8, "EDGE_SE3:QUAT": 30}
        if tag == "FIX":
            fixed.update(int(t) for t in tokens[1:])
            continue
        if tag not in expected:
            if skip_unknown:
                continue
            raise ValueError(f"{where}: unsupported record `{tag}`")
        if len(tokens) - 1 < expected[tag]:
            raise ValueError(f"{where}: {tag} needs {expected[tag]} fields, got {len(tokens) - 1}")
        try:
            f = [float(t) for t in tokens[1:1 + expected[tag]]]
        except ValueError:
            raise ValueError(f"{where}: {tag} has a field that is not a number") from None
        if tag == "VERTEX_SE2":
            dim(2, where)
            key = int(f[0])
            if key in vertices:
                raise ValueError(f"{where}: vertex {key} defined twice")
            vertices[key] = f[1:4]
        elif tag == "VERTEX_SE3:QUAT":
            dim(3, where)
            key = int(f[0])
            if key in vertices:
                raise ValueError(f"{where}: vertex {key} defined twice")
            vertices[key] = f[1:4] + _normalised(f[4:8], where)
        elif tag == "EDGE_SE2":
            dim(2, where)
            info = f[5:11]
            edges.append(Edge(int(f[0]), int(f[1]), f[2:5], list(info), list(info), number))
        else:  # EDGE_SE3:QUAT
            dim(3, where)
            info = f[9:30]
            measurement = f[2:5] + _normalised(f[5:9], where)
            edges.append(Edge(int(f[0]), int(f[1]), measurement, _scale_information_3d(info),
                              list(info), number))
    if dimension is None or not vertices:
        raise ValueError(f"{name}: no vertices")
    for e in edges:
        for k in (e.i, e.j):
            if k not in vertices:
                raise ValueError(f"{name}:{e.line}: edge names vertex {k}, which is not defined")
        if e.i == e.j:
            raise ValueError(f"{name}:{e.line}: edge joins vertex {e.i} to itself")
    for k in fixed:
        if k not in vertices:
            raise ValueError(f"{name}: FIX names vertex {k}, which is not defined")
    return Graph(dimension=dimension, vertices=vertices, edges=edges, fixed=fixed)


def load(path: Union[str, "os.PathLike[str]"], skip_unknown: bool = False) -> Graph:
    """Reads and parses a g2o file."""
    with open(path, encoding="utf-8") as f:
        return parse(f.read(), name=os.fspath(path), skip_unknown=skip_unknown)


def stream_batches(graph: Graph, predict: bool = True,
                   limit: Optional[int] = None) -> Iterator[Tuple[int, JsonDict]]:
    """Same as :meth:`Graph.batches`."""
    return graph.batches(predict=predict, limit=limit)
