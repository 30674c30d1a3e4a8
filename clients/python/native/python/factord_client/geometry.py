"""Poses and noise models in numpy, converting to and from factord's wire encodings.

* :class:`Pose2` — SE(2) ``[x, y, θ]`` (wire kind ``se2``);
* :class:`Pose3` — SE(3) ``[x, y, z, qx, qy, qz, qw]`` (wire kind ``se3``, scalar-last
  quaternion as g2o);
* :class:`Noise` — a Gaussian noise model from sigmas, a covariance or an information matrix;
  a factor receives its information matrix (the inverse covariance).

The group operations follow GTSAM's names: ``a.compose(b)`` (also ``a * b``), ``a.inverse()``,
``a.between(b)`` = ``a⁻¹ b``, the pose of ``b`` in ``a``'s frame, which is what a
``between_se2`` / ``between_se3`` factor from ``a`` to ``b`` measures.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, List, Optional, Sequence, Union

import numpy as np

from .wire import VariableSpec

ArrayLike = Union[Sequence[float], np.ndarray]


def wrap_angle(theta: float) -> float:
    """θ wrapped to (-π, π], as the server wraps se2 headings."""
    wrapped = math.atan2(math.sin(theta), math.cos(theta))
    return math.pi if wrapped == -math.pi else wrapped


def _vector(values: Any, length: int, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=float).reshape(-1)
    if array.shape != (length,):
        raise ValueError(f"{what} needs {length} numbers, got shape {np.shape(values)}")
    return array


def _variable(key: int, kind: str, value: List[float], stamp: Optional[float],
              fixed: bool) -> VariableSpec:
    spec: VariableSpec = {"key": int(key), "kind": kind, "value": value}
    if stamp is not None:
        spec["stamp"] = float(stamp)
    if fixed:
        spec["fixed"] = True
    return spec


class Pose2:
    """A 2D pose: position ``(x, y)`` and heading ``theta`` (radians, wrapped to (-π, π])."""

    __slots__ = ("x", "y", "theta")
    kind = "se2"

    def __init__(self, x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> None:
        self.x = float(x)
        self.y = float(y)
        self.theta = wrap_angle(float(theta))

    # ------------------------------------------------------------ conversions
    @classmethod
    def from_array(cls, values: ArrayLike) -> "Pose2":
        """From ``[x, y, θ]`` (the wire encoding, a row of ``estimate_array``)."""
        x, y, theta = _vector(values, 3, "Pose2")
        return cls(x, y, theta)

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> "Pose2":
        """From a 3×3 homogeneous transform."""
        m = np.asarray(matrix, dtype=float)
        if m.shape != (3, 3):
            raise ValueError(f"Pose2.from_matrix needs a 3x3 matrix, got {m.shape}")
        return cls(m[0, 2], m[1, 2], math.atan2(m[1, 0], m[0, 0]))

    def to_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.theta])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        array = self.to_array()
        return array if dtype is None else array.astype(dtype)

    def to_wire(self) -> List[float]:
        """The ``se2`` wire encoding ``[x, y, θ]``."""
        return [self.x, self.y, self.theta]

    def matrix(self) -> np.ndarray:
        """The 3×3 homogeneous transform (world from body)."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def translation(self) -> np.ndarray:
        return np.array([self.x, self.y])

    def variable(self, key: int, stamp: Optional[float] = None,
                 fixed: bool = False) -> VariableSpec:
        """This pose as a new variable of a batch (``stamp``: seconds, for TUM exports)."""
        return _variable(key, self.kind, self.to_wire(), stamp, fixed)

    # ------------------------------------------------------------ group operations
    def compose(self, other: "Pose2") -> "Pose2":
        """``self * other``: ``other`` (expressed in this pose's frame) in the world frame."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2(self.x + c * other.x - s * other.y, self.y + s * other.x + c * other.y,
                     self.theta + other.theta)

    def inverse(self) -> "Pose2":
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2(-c * self.x - s * self.y, s * self.x - c * self.y, -self.theta)

    def between(self, other: "Pose2") -> "Pose2":
        """``self⁻¹ * other``: the measurement of a ``between_se2`` factor from self to other."""
        return self.inverse().compose(other)

    def transform_from(self, point: ArrayLike) -> np.ndarray:
        """A point given in this pose's frame, in the world frame."""
        p = _vector(point, 2, "point")
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([self.x + c * p[0] - s * p[1], self.y + s * p[0] + c * p[1]])

    def __mul__(self, other: "Pose2") -> "Pose2":
        return self.compose(other)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Pose2) and self.to_wire() == other.to_wire()

    def __hash__(self) -> int:
        return hash((self.x, self.y, self.theta))

    def almost_equal(self, other: "Pose2", tol: float = 1e-9) -> bool:
        d = self.between(other)
        return abs(d.x) <= tol and abs(d.y) <= tol and abs(d.theta) <= tol

    def __repr__(self) -> str:
        return f"Pose2(x={self.x:.6g}, y={self.y:.6g}, theta={self.theta:.6g})"


def _quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-last quaternions ``[x, y, z, w]``."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _quaternion_from_matrix(r: np.ndarray) -> np.ndarray:
    """Scalar-last unit quaternion of a rotation matrix (Shepperd's method: the largest
    diagonal term first, so no division by a small number)."""
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    return _canonical(np.array(q))


def _canonical(q: np.ndarray) -> np.ndarray:
    """Unit norm and w ≥ 0 (q and -q are the same rotation; one spelling compares equal)."""
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"not a rotation quaternion: {q}")
    q = q / norm
    return -q if q[3] < 0 else q


class Pose3:
    """A 3D pose: ``translation`` (3,) and rotation as a unit quaternion ``quaternion``
    ``[qx, qy, qz, qw]`` (scalar last, normalised)."""

    __slots__ = ("translation", "quaternion")
    kind = "se3"

    def __init__(self, translation: ArrayLike = (0.0, 0.0, 0.0),
                 quaternion: ArrayLike = (0.0, 0.0, 0.0, 1.0)) -> None:
        self.translation = _vector(translation, 3, "Pose3 translation")
        self.quaternion = _canonical(_vector(quaternion, 4, "Pose3 quaternion"))

    # ------------------------------------------------------------ conversions
    @classmethod
    def from_array(cls, values: ArrayLike) -> "Pose3":
        """From ``[x, y, z, qx, qy, qz, qw]`` (the wire encoding)."""
        v = _vector(values, 7, "Pose3")
        return cls(v[:3], v[3:])

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> "Pose3":
        """From a 4×4 homogeneous transform (or a 3×4 ``[R | t]``, as a KITTI row)."""
        m = np.asarray(matrix, dtype=float)
        if m.shape == (12,):
            m = m.reshape(3, 4)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"Pose3.from_matrix needs a 4x4 or 3x4 matrix, got {m.shape}")
        return cls(m[:3, 3], _quaternion_from_matrix(m[:3, :3]))

    @classmethod
    def from_rotation_vector(cls, rotation_vector: ArrayLike,
                             translation: ArrayLike = (0.0, 0.0, 0.0)) -> "Pose3":
        """From an angle-axis vector (radians) and a translation."""
        w = _vector(rotation_vector, 3, "rotation vector")
        angle = float(np.linalg.norm(w))
        if angle < 1e-12:
            q = np.array([w[0] / 2, w[1] / 2, w[2] / 2, 1.0])
        else:
            axis = w / angle
            q = np.append(axis * math.sin(angle / 2), math.cos(angle / 2))
        return cls(translation, q)

    def to_array(self) -> np.ndarray:
        return np.concatenate([self.translation, self.quaternion])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        array = self.to_array()
        return array if dtype is None else array.astype(dtype)

    def to_wire(self) -> List[float]:
        """The ``se3`` wire encoding ``[x, y, z, qx, qy, qz, qw]``."""
        return [float(v) for v in self.to_array()]

    def rotation_matrix(self) -> np.ndarray:
        return _rotation_matrix(self.quaternion)

    def matrix(self) -> np.ndarray:
        """The 4×4 homogeneous transform (world from body)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation_matrix()
        m[:3, 3] = self.translation
        return m

    def variable(self, key: int, stamp: Optional[float] = None,
                 fixed: bool = False) -> VariableSpec:
        """This pose as a new variable of a batch (``stamp``: seconds, for TUM exports)."""
        return _variable(key, self.kind, self.to_wire(), stamp, fixed)

    # ------------------------------------------------------------ group operations
    def compose(self, other: "Pose3") -> "Pose3":
        return Pose3(self.translation + self.rotation_matrix() @ other.translation,
                     _quaternion_multiply(self.quaternion, other.quaternion))

    def inverse(self) -> "Pose3":
        conjugate = self.quaternion * np.array([-1.0, -1.0, -1.0, 1.0])
        return Pose3(-(self.rotation_matrix().T @ self.translation), conjugate)

    def between(self, other: "Pose3") -> "Pose3":
        """``self⁻¹ * other``: the measurement of a ``between_se3`` factor from self to other."""
        return self.inverse().compose(other)

    def transform_from(self, point: ArrayLike) -> np.ndarray:
        return self.translation + self.rotation_matrix() @ _vector(point, 3, "point")

    def __mul__(self, other: "Pose3") -> "Pose3":
        return self.compose(other)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Pose3) and self.to_wire() == other.to_wire()

    def __hash__(self) -> int:
        return hash(tuple(self.to_wire()))

    def almost_equal(self, other: "Pose3", tol: float = 1e-9) -> bool:
        d = self.between(other)
        return bool(np.all(np.abs(d.translation) <= tol)
                    and np.all(np.abs(d.quaternion[:3]) <= tol))

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.6g}" for v in self.translation)
        q = ", ".join(f"{v:.6g}" for v in self.quaternion)
        return f"Pose3(translation=[{t}], quaternion=[{q}])"


AnyPose = Union[Pose2, Pose3]


def pose_from_wire(kind: str, value: ArrayLike) -> AnyPose:
    """``se2`` → :class:`Pose2`, ``se3`` → :class:`Pose3`."""
    if kind == "se2":
        return Pose2.from_array(value)
    if kind == "se3":
        return Pose3.from_array(value)
    raise ValueError(f"`{kind}` is not a pose kind (se2 or se3)")


def upper_triangle(matrix: np.ndarray) -> List[float]:
    """The d(d+1)/2 upper-triangle entries, row by row (g2o's order, what factors take)."""
    rows, cols = np.triu_indices(matrix.shape[0])
    return [float(v) for v in matrix[rows, cols]]


class Noise:
    """A Gaussian noise model of dimension ``dim`` for one factor.

    >>> Noise.sigmas([0.1, 0.1, 0.05])             # sent as `sigmas`
    >>> Noise.covariance(np.diag([0.01, 0.01, 0.0025]))   # sent as `information` = inverse
    >>> Noise.information(info_matrix)              # sent as given (upper triangle)
    >>> Noise.isotropic(3, 0.1)

    A covariance must be symmetric positive definite (its Cholesky factorisation is tried; a
    ``ValueError`` names the problem); the information matrix sent is its inverse, symmetrised.
    """

    __slots__ = ("information_matrix", "_sigmas")

    def __init__(self, information_matrix: ArrayLike,
                 sigmas: Optional[np.ndarray] = None) -> None:
        info = np.asarray(information_matrix, dtype=float)
        if info.ndim != 2 or info.shape[0] != info.shape[1] or info.shape[0] == 0:
            raise ValueError(f"an information matrix must be square, got shape {info.shape}")
        if not np.all(np.isfinite(info)):
            raise ValueError("the information matrix has non-finite entries")
        self.information_matrix = (info + info.T) / 2.0
        self._sigmas = sigmas

    @classmethod
    def sigmas(cls, sigmas: ArrayLike) -> "Noise":
        s = np.asarray(sigmas, dtype=float).reshape(-1)
        if s.size == 0 or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"sigmas must be finite and positive, got {s}")
        return cls(np.diag(1.0 / s**2), sigmas=s)

    @classmethod
    def isotropic(cls, dim: int, sigma: float) -> "Noise":
        return cls.sigmas(np.full(int(dim), float(sigma)))

    @classmethod
    def covariance(cls, covariance: ArrayLike) -> "Noise":
        cov = np.asarray(covariance, dtype=float)
        if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
            raise ValueError(f"a covariance must be square, got shape {cov.shape}")
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(cov).max())):
            raise ValueError("a covariance must be symmetric")
        try:
            factor = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise ValueError("a covariance must be positive definite") from None
        # inv(L L^T) through the triangular factor: better conditioned than inv(cov).
        inverse_factor = np.linalg.inv(factor)
        return cls(inverse_factor.T @ inverse_factor)

    @classmethod
    def information(cls, information: ArrayLike) -> "Noise":
        """From an information matrix (d×d) or its upper triangle (d(d+1)/2 numbers)."""
        info = np.asarray(information, dtype=float)
        if info.ndim == 1:
            info = _from_upper_triangle(info)
        return cls(info)

    @property
    def dim(self) -> int:
        return int(self.information_matrix.shape[0])

    @property
    def covariance_matrix(self) -> np.ndarray:
        return np.linalg.inv(self.information_matrix)

    def to_wire(self) -> dict:
        """The factor fields: ``{"sigmas": [...]}`` when built from sigmas, else
        ``{"information": upper triangle}``."""
        if self._sigmas is not None:
            return {"sigmas": [float(v) for v in self._sigmas]}
        return {"information": upper_triangle(self.information_matrix)}

    def __repr__(self) -> str:
        if self._sigmas is not None:
            return f"Noise.sigmas({[float(v) for v in self._sigmas]})"
        return f"Noise.information({self.information_matrix.tolist()})"


def _from_upper_triangle(values: np.ndarray) -> np.ndarray:
    n = len(values)
    dim = int(round((math.sqrt(8 * n + 1) - 1) / 2))
    if dim * (dim + 1) // 2 != n:
        raise ValueError(f"{n} numbers are not the upper triangle of a square matrix")
    matrix = np.zeros((dim, dim))
    rows, cols = np.triu_indices(dim)
    matrix[rows, cols] = values
    matrix[cols, rows] = values
    return matrix


def information_rows(information: Any, count: int, dim: int) -> List[List[float]]:
    """Per-factor information for ``count`` factors of dimension ``dim``, as wire lists (upper
    triangles) from: one :class:`Noise`, one d×d matrix or upper triangle (shared), an (M, d, d)
    stack or an (M, d(d+1)/2) array of upper triangles (one per factor)."""
    if isinstance(information, Noise):
        return [upper_triangle(information.information_matrix)] * count
    info = np.asarray(information, dtype=float)
    triangle = dim * (dim + 1) // 2
    if info.shape == (dim, dim):
        return [upper_triangle((info + info.T) / 2)] * count
    if info.shape == (triangle,):
        return [[float(v) for v in info]] * count
    if info.shape == (count, dim, dim):
        rows, cols = np.triu_indices(dim)
        return info[:, rows, cols].tolist()
    if info.shape == (count, triangle):
        return info.tolist()
    raise ValueError(f"information for {count} factors of dimension {dim}: expected a Noise, "
                     f"({dim}, {dim}), ({triangle},), ({count}, {dim}, {dim}) or "
                     f"({count}, {triangle}); got {info.shape}")


def as_poses(kind: str, values: Iterable[ArrayLike]) -> List[AnyPose]:
    return [pose_from_wire(kind, v) for v in values]
