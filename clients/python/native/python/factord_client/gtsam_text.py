"""GTSAM's 2D landmark text (``ODOMETRY``, ``LANDMARK``; e.g. Victoria Park) as factord batches,
read the way GTSAM's ``load2D`` and factord's own reader (``src/io/gtsam_text.rs``) read it:

* ``ODOMETRY i j dx dy dtheta c1..c6``: a ``between_se2``. Six numbers ``a 0 0 b 0 c`` are a
  covariance ``xx xy xtheta yy ytheta thetatheta`` (inverted here), ``a 0 b c 0 0`` TORO's
  information ``xx xy yy tt xt yt`` (reordered to the wire's upper triangle).
* ``LANDMARK i l x y v1 v2 v3``: a ``bearing_range_se2`` from pose i to landmark l seen at
  body-frame (x, y): bearing ``atan2(y, x)``, range ``hypot(x, y)``, sigmas ``sqrt(v1/10)`` and
  ``sqrt(v1)`` when ``|v1 - v3| < 1e-4``, else 1 and 1.
* Landmark l is the key ``(ord('l') << 56) | l`` (GTSAM's ``Symbol('l', l)``).

Streaming order (``batches``), as ``benches/incremental/serve/landmarks.rs``: per pose id, the pose
(a value only for the first: the server predicts the others from their odometry), the odometry
that ends at it, the landmarks first seen from it (no value: the server starts each from that
sighting) and every sighting from it.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Optional, Set, Tuple, Union

JsonDict = Dict[str, Any]

LANDMARK_TAG = ord("l") << 56


def landmark_key(l: int) -> int:
    """The key of landmark ``l``: GTSAM's ``Symbol('l', l)``."""
    return LANDMARK_TAG | l


def is_gtsam_text(path: Union[str, "os.PathLike[str]"]) -> bool:
    """Whether the file's first record is ``ODOMETRY`` or ``LANDMARK``."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            tokens = line.split()
            if tokens and not tokens[0].startswith("#"):
                return tokens[0] in ("ODOMETRY", "LANDMARK")
    return False


def _information(c: List[float], where: str) -> List[float]:
    """The wire upper triangle (xx xy xt yy yt tt) of an ODOMETRY record's six numbers."""
    if c[0] != 0 and c[1] == 0 and c[2] == 0 and c[3] != 0 and c[4] == 0 and c[5] != 0:
        m = [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
        det = (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
               - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
               + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
        if det == 0:
            raise ValueError(f"{where}: the covariance is not invertible")
        inv = [[(m[(r + 1) % 3][(k + 1) % 3] * m[(r + 2) % 3][(k + 2) % 3]
                 - m[(r + 1) % 3][(k + 2) % 3] * m[(r + 2) % 3][(k + 1) % 3]) / det
                for r in range(3)] for k in range(3)]
        return [inv[0][0], inv[0][1], inv[0][2], inv[1][1], inv[1][2], inv[2][2]]
    xx, xy, yy, tt, xt, yt = c
    return [xx, xy, xt, yy, yt, tt]


@dataclass
class LandmarkGraph:
    #: pose id -> its ODOMETRY factors ending there and its sightings, in file order
    odometry: Dict[int, List[JsonDict]] = field(default_factory=dict)
    sightings: Dict[int, List[JsonDict]] = field(default_factory=dict)
    poses: List[int] = field(default_factory=list)
    landmarks: List[int] = field(default_factory=list)

    session_kind = "pose_graph_2d"

    @property
    def vertices(self) -> List[int]:
        """Every variable key: poses, then landmarks."""
        return self.poses + self.landmarks

    @property
    def edges(self) -> List[JsonDict]:
        """Every factor."""
        return [f for k in self.poses for f in self.odometry.get(k, []) + self.sightings.get(k, [])]

    def batches(self, predict: bool = True, limit: Optional[int] = None) -> Iterator[Tuple[int, JsonDict]]:
        """``(pose id, batch)`` in streaming order (module doc); ``limit``: the first N poses.
        ``predict=False`` is refused: poses have no values in this format."""
        if not predict:
            raise ValueError("a GTSAM landmark file has no pose values; the server predicts them")
        seen = set()
        for n, k in enumerate(self.poses):
            if limit is not None and n >= limit:
                return
            pose: JsonDict = {"key": k, "kind": "se2"}
            if n == 0:
                pose["value"] = [0.0, 0.0, 0.0]
            variables = [pose]
            for f in self.sightings.get(k, []):
                l = f["keys"][1]
                if l not in seen:
                    seen.add(l)
                    variables.append({"key": l, "kind": "point2"})
            yield k, {"variables": variables,
                      "factors": self.odometry.get(k, []) + self.sightings.get(k, [])}


def parse(text: str, name: str = "<gtsam>") -> LandmarkGraph:
    g = LandmarkGraph()
    poses: Set[int] = set()
    landmarks: Dict[int, None] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{name}:{number}"
        tag = tokens[0]
        expected = {"ODOMETRY": 11, "LANDMARK": 7}.get(tag)
        if expected is None:
            raise ValueError(f"{where}: unsupported record `{tag}` (ODOMETRY, LANDMARK)")
        if len(tokens) - 1 != expected:
            raise ValueError(f"{where}: {tag} needs {expected} fields, got {len(tokens) - 1}")
        try:
            f = [float(t) for t in tokens[1:]]
        except ValueError:
            raise ValueError(f"{where}: {tag} has a field that is not a number") from None
        if tag == "ODOMETRY":
            i, j = int(f[0]), int(f[1])
            poses.update((i, j))
            g.odometry.setdefault(max(i, j), []).append({
                "type": "between_se2", "keys": [i, j], "measurement": f[2:5],
                "information": _information(f[5:11], where)})
        else:
            i, l, x, y, v1, _, v3 = int(f[0]), int(f[1]), f[2], f[3], f[4], f[5], f[6]
            if x == 0 and y == 0:
                raise ValueError(f"{where}: a landmark at the pose itself has no bearing")
            sb, sr = ((math.sqrt(v1 / 10), math.sqrt(v1)) if abs(v1 - v3) < 1e-4 and v1 > 0
                      else (1.0, 1.0))
            poses.add(i)
            landmarks[landmark_key(l)] = None
            g.sightings.setdefault(i, []).append({
                "type": "bearing_range_se2", "keys": [i, landmark_key(l)],
                "measurement": [math.atan2(y, x), math.hypot(x, y)], "sigmas": [sb, sr]})
    if not poses:
        raise ValueError(f"{name}: no records")
    g.poses = sorted(poses)
    g.landmarks = list(landmarks)
    return g


def load(path: Union[str, "os.PathLike[str]"]) -> LandmarkGraph:
    """Reads and parses a GTSAM landmark text file."""
    with open(path, encoding="utf-8") as f:
        return parse(f.read(), name=os.fspath(path))
