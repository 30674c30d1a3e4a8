"""Building batches from numpy arrays and poses, encoding them as JSON, and reading estimates
and covariances back as arrays.

:class:`Batch` collects variables and factors (one at a time or whole arrays at once) and is
accepted wherever a batch dict is (``apply_batch``, producers' ``send``). :func:`dumps` is the
JSON encoder every client uses: numpy arrays and scalars, :class:`Pose2` / :class:`Pose3`,
:class:`Noise` and :class:`Batch` may appear anywhere in a request.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import AnyPose, Noise, Pose2, Pose3, information_rows, pose_from_wire
from .wire import Batch as BatchDict
from .wire import Estimate, FactorSpec, GuessSpec, Marginals, RobustKernel, VariableSpec

ArrayLike = Union[Sequence[Any], np.ndarray]

# Residual dimension and measurement length of the built-in factor types the helpers infer.
_BETWEEN = {"se2": ("between_se2", 3), "se3": ("between_se3", 6)}
_PRIOR = {"se2": ("prior_se2", 3), "se3": ("prior_se3", 6)}
_WIRE_LENGTH = {"se2": 3, "se3": 7, "point2": 2, "point3": 3, "snavely_camera": 9}


def _json_default(value: Any) -> Any:
    """What :mod:`json` cannot encode by itself: numpy values, poses, noise, batches."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    to_wire = getattr(value, "to_wire", None)
    if callable(to_wire):
        return to_wire()
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable "
                    "(factord_client encodes numpy arrays, poses, Noise and Batch)")


def dumps(value: Any) -> str:
    """JSON text of a request, numpy arrays and the helpers' objects included."""
    return json.dumps(value, default=_json_default)


def jsonable(value: Any) -> Any:
    """The same value with plain lists, floats and ints only (e.g. to edit a batch as a dict)."""
    return json.loads(dumps(value))


def _keys(keys: ArrayLike, what: str) -> List[int]:
    array = np.asarray(keys)
    if array.ndim != 1:
        raise ValueError(f"{what} must be one key per row, got shape {array.shape}")
    if array.size and not np.all(np.equal(np.mod(array, 1), 0)):
        raise ValueError(f"{what} must be whole numbers")
    return [int(k) for k in array]


def _rows(values: ArrayLike, count: int, length: int, what: str) -> List[List[float]]:
    array = np.asarray(values, dtype=float)
    if array.shape == (length,) and count == 1:
        array = array.reshape(1, length)
    if array.shape != (count, length):
        raise ValueError(f"{what}: expected shape ({count}, {length}), got {array.shape}")
    return array.tolist()


def _noise_fields(noise: Any, dim: int) -> Dict[str, Any]:
    """``{"information": ...}`` or ``{"sigmas": ...}`` from a :class:`Noise` or raw values."""
    if noise is None:
        raise ValueError("a factor needs a noise model (noise=Noise.sigmas([...]), ...)")
    if not isinstance(noise, Noise):
        noise = Noise.information(noise)
    if noise.dim != dim:
        raise ValueError(f"noise of dimension {noise.dim} for a factor of dimension {dim}")
    return noise.to_wire()


class Batch:
    """A batch under construction (see ``batch.schema.json``): methods return ``self`` so calls
    chain, and :meth:`to_wire` gives the dict sent.

    >>> b = Batch().pose(0, Pose2(0, 0, 0), stamp=0.0, fixed=True)
    >>> b.pose(1, None).between(0, 1, Pose2(1, 0, 0.1), Noise.sigmas([0.1, 0.1, 0.05]))
    >>> Batch().poses(keys, values_n3).between_many(pairs_m2, measurements_m3, information_m6)
    """

    def __init__(self) -> None:
        self.variables: List[VariableSpec] = []
        self.factors: List[FactorSpec] = []
        self.fixed_keys: List[int] = []
        self.guesses: List[GuessSpec] = []
        self.removed_factors: List[int] = []

    # ------------------------------------------------------------ variables
    def variable(self, key: int, kind: str, value: Optional[ArrayLike] = None,
                 stamp: Optional[float] = None, fixed: bool = False) -> "Batch":
        """A new variable; ``value`` ``None`` lets the server predict it from an odometry
        factor of this batch."""
        spec: VariableSpec = {"key": int(key), "kind": kind}
        if value is not None:
            spec["value"] = [float(v) for v in np.asarray(value, dtype=float).reshape(-1)]
        if stamp is not None:
            spec["stamp"] = float(stamp)
        if fixed:
            spec["fixed"] = True
        self.variables.append(spec)
        return self

    def pose(self, key: int, pose: Union[AnyPose, ArrayLike, None], kind: Optional[str] = None,
             stamp: Optional[float] = None, fixed: bool = False) -> "Batch":
        """A new pose variable from a :class:`Pose2` / :class:`Pose3` (kind inferred), an array
        (``[x, y, θ]`` is se2, 7 numbers se3, unless ``kind`` says) or ``None`` (predicted)."""
        if isinstance(pose, (Pose2, Pose3)):
            return self.variable(key, pose.kind, pose.to_wire(), stamp, fixed)
        if pose is None:
            if kind is None:
                raise ValueError("a predicted pose (no value) needs its kind")
            return self.variable(key, kind, None, stamp, fixed)
        value = np.asarray(pose, dtype=float).reshape(-1)
        return self.variable(key, kind or _pose_kind(len(value)), value, stamp, fixed)

    def poses(self, keys: ArrayLike, values: ArrayLike, kind: Optional[str] = None,
              stamps: Optional[ArrayLike] = None, fixed: bool = False) -> "Batch":
        """Many new variables at once: ``keys`` (N,), ``values`` (N, d) in the wire encoding
        (kind from d: 3 is se2, 7 se3, unless ``kind`` says), ``stamps`` (N,) seconds."""
        key_list = _keys(keys, "keys")
        array = np.asarray(values, dtype=float)
        if array.ndim != 2:
            raise ValueError(f"values must be one row per key, got shape {array.shape}")
        chosen_kind = kind or _pose_kind(array.shape[1])
        length = int(_WIRE_LENGTH.get(chosen_kind) or array.shape[1])
        rows = _rows(array, len(key_list), length, "values")
        stamp_list: List[Optional[float]] = [None] * len(key_list)
        if stamps is not None:
            stamp_list = [float(s) for s in np.asarray(stamps, dtype=float).reshape(-1)]
            if len(stamp_list) != len(key_list):
                raise ValueError(f"{len(stamp_list)} stamps for {len(key_list)} keys")
        for key, row, stamp in zip(key_list, rows, stamp_list):
            self.variable(key, chosen_kind, row, stamp, fixed)
        return self

    # ------------------------------------------------------------ factors
    def factor(self, type: str, keys: ArrayLike, measurement: Union[AnyPose, ArrayLike],
               noise: Any = None, robust: Optional[RobustKernel] = None) -> "Batch":
        """Any factor type (built-in or user-defined). ``noise``: a :class:`Noise`, or an
        information matrix / upper triangle; the dimension is checked by the server."""
        spec: Dict[str, Any] = {"type": type, "keys": _keys(keys, "keys"),
                                "measurement": _measurement(measurement)}
        if isinstance(noise, Noise):
            spec.update(noise.to_wire())
        elif noise is not None:
            spec.update(Noise.information(noise).to_wire())
        else:
            raise ValueError("a factor needs a noise model (noise=Noise.sigmas([...]), ...)")
        if robust is not None:
            spec["robust"] = robust
        self.factors.append(spec)  # type: ignore[arg-type]
        return self

    def between(self, i: int, j: int, measurement: Union[AnyPose, ArrayLike], noise: Any,
                robust: Optional[RobustKernel] = None) -> "Batch":
        """A relative pose (odometry, loop closure): the pose of ``j`` in ``i``'s frame;
        ``between_se2`` for a :class:`Pose2` / 3 numbers, ``between_se3`` for 7."""
        kind = _measurement_kind(measurement)
        factor_type, dim = _BETWEEN[kind]
        return self._checked(factor_type, [i, j], measurement, noise, dim, robust)

    def prior(self, key: int, value: Union[AnyPose, ArrayLike], noise: Any,
              robust: Optional[RobustKernel] = None) -> "Batch":
        """An absolute pose: ``prior_se2`` / ``prior_se3``."""
        factor_type, dim = _PRIOR[_measurement_kind(value)]
        return self._checked(factor_type, [key], value, noise, dim, robust)

    def _checked(self, factor_type: str, keys: List[int], measurement: Any, noise: Any,
                 dim: int, robust: Optional[RobustKernel]) -> "Batch":
        spec: Dict[str, Any] = {"type": factor_type, "keys": _keys(keys, "keys"),
                                "measurement": _measurement(measurement),
                                **_noise_fields(noise, dim)}
        if robust is not None:
            spec["robust"] = robust
        self.factors.append(spec)  # type: ignore[arg-type]
        return self

    def between_many(self, pairs: ArrayLike, measurements: ArrayLike, information: Any,
                     kind: Optional[str] = None) -> "Batch":
        """Many relative poses at once: ``pairs`` (M, 2) keys, ``measurements`` (M, 3) or
        (M, 7), ``information`` one :class:`Noise` / matrix for all, (M, d, d) or the
        (M, d(d+1)/2) upper triangles (g2o's EDGE_SE2 columns)."""
        pair_array = np.asarray(pairs)
        if pair_array.ndim != 2 or pair_array.shape[1] != 2:
            raise ValueError(f"pairs must have shape (M, 2), got {pair_array.shape}")
        meas = np.asarray(measurements, dtype=float)
        if meas.ndim != 2:
            raise ValueError(f"measurements must have shape (M, 3) or (M, 7), got {meas.shape}")
        factor_type, dim = _BETWEEN[kind or _pose_kind(meas.shape[1])]
        count = len(pair_array)
        rows = _rows(meas, count, meas.shape[1], "measurements")
        infos = information_rows(information, count, dim)
        for (i, j), row, info in zip(pair_array.tolist(), rows, infos):
            self.factors.append({"type": factor_type, "keys": [int(i), int(j)],
                                 "measurement": row, "information": info})
        return self

    # ------------------------------------------------------------ the rest
    def fix(self, *keys: int) -> "Batch":
        self.fixed_keys.extend(int(k) for k in keys)
        return self

    def guess(self, key: int, value: Union[AnyPose, ArrayLike]) -> "Batch":
        """A new value for an existing variable (re-seed after a relocalisation)."""
        self.guesses.append({"key": int(key), "value": _measurement(value)})
        return self

    def remove_factors(self, *factor_ids: int) -> "Batch":
        self.removed_factors.extend(int(f) for f in factor_ids)
        return self

    def to_wire(self) -> BatchDict:
        batch: BatchDict = {}
        if self.variables:
            batch["variables"] = list(self.variables)
        if self.factors:
            batch["factors"] = list(self.factors)
        if self.fixed_keys:
            batch["fix"] = list(self.fixed_keys)
        if self.guesses:
            batch["guesses"] = list(self.guesses)
        if self.removed_factors:
            batch["remove_factors"] = list(self.removed_factors)
        return batch

    def __len__(self) -> int:
        return len(self.variables) + len(self.factors)

    def __repr__(self) -> str:
        return f"Batch({len(self.variables)} variables, {len(self.factors)} factors)"


def as_batch(batch: Union[Batch, BatchDict, Dict[str, Any]]) -> Dict[str, Any]:
    """A batch dict with plain JSON values, from a :class:`Batch` or a dict that may hold
    numpy arrays and poses (producers add their fields to it)."""
    return jsonable(batch.to_wire() if isinstance(batch, Batch) else batch)


def _pose_kind(length: int) -> str:
    if length == 3:
        return "se2"
    if length == 7:
        return "se3"
    raise ValueError(f"{length} numbers are no pose (se2 has 3, se3 7); pass kind=")


def _measurement_kind(measurement: Any) -> str:
    if isinstance(measurement, (Pose2, Pose3)):
        return measurement.kind
    return _pose_kind(np.asarray(measurement).size)


def _measurement(measurement: Any) -> List[float]:
    if isinstance(measurement, (Pose2, Pose3)):
        return measurement.to_wire()
    return [float(v) for v in np.asarray(measurement, dtype=float).reshape(-1)]


# ---------------------------------------------------------------- answers as arrays
@dataclass
class EstimateArray:
    """Variables of one kind as arrays: ``keys`` (N,) int64, ``values`` (N, d) in the wire
    encoding (se2 (N, 3) ``[x, y, θ]``, se3 (N, 7) ``[x, y, z, qx, qy, qz, qw]``), ``stamps``
    (N,) seconds (NaN where a variable has none), sorted by key. Unpacks as
    ``keys, values = client.estimate_array(session)``."""

    kind: str
    keys: np.ndarray
    values: np.ndarray
    stamps: np.ndarray
    sequence: int = 0
    session: str = ""
    extra_kinds: List[str] = field(default_factory=list)
    #: (N,) the sequence that last changed each value (binary estimates; None from JSON).
    changed: Optional[np.ndarray] = None

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter((self.keys, self.values))

    def __len__(self) -> int:
        return len(self.keys)

    def poses(self) -> Dict[int, AnyPose]:
        """``{key: Pose2 | Pose3}``."""
        return {int(k): pose_from_wire(self.kind, v) for k, v in zip(self.keys, self.values)}

    def value(self, key: int) -> np.ndarray:
        index = np.searchsorted(self.keys, key)
        if index >= len(self.keys) or self.keys[index] != key:
            raise KeyError(key)
        return self.values[index]


def estimate_to_array(estimate: Estimate, kind: Optional[str] = None) -> EstimateArray:
    """An estimate answer as an :class:`EstimateArray` of one kind: ``kind`` when given, else
    the only kind, else the only pose kind (se2 or se3) among several (landmarks are left out;
    ask for them with ``kind="point2"``)."""
    variables = estimate["variables"]
    kinds = sorted({v["kind"] for v in variables})
    if kind is None:
        pose_kinds = [k for k in kinds if k in ("se2", "se3")]
        if len(kinds) == 1:
            kind = kinds[0]
        elif len(pose_kinds) == 1:
            kind = pose_kinds[0]
        elif not kinds:
            kind = "se2"
        else:
            raise ValueError(f"the estimate holds kinds {kinds}: pass kind=")
    chosen = sorted((v for v in variables if v["kind"] == kind), key=lambda v: v["key"])
    length = _WIRE_LENGTH.get(kind, len(chosen[0]["value"]) if chosen else 0)
    values = np.array([v["value"] for v in chosen], dtype=float).reshape(len(chosen), length)
    return EstimateArray(
        kind=kind,
        keys=np.array([v["key"] for v in chosen], dtype=np.int64),
        values=values,
        stamps=np.array([v.get("stamp", np.nan) for v in chosen], dtype=float),
        sequence=int(estimate.get("sequence", 0)),
        session=str(estimate.get("session", "")),
        extra_kinds=[k for k in kinds if k != kind],
    )


def marginals_to_arrays(marginals: Marginals) -> Tuple[Dict[int, np.ndarray],
                                                       Optional[np.ndarray]]:
    """``({key: covariance (d, d)}, joint (n, n) or None)`` from a marginals answer."""
    covariances = {int(v["key"]): np.array(v["covariance"], dtype=float)
                   for v in marginals["variables"]}
    joint = marginals.get("joint")
    return covariances, (np.array(joint, dtype=float) if joint is not None else None)
