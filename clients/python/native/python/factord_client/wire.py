"""The JSON shapes of factord's wire protocol as ``TypedDict``\\ s, so that a type checker
(mypy, pyright) sees what a method takes and answers. They mirror ``proto/v1/*.schema.json``;
the schemas stay the authority (they are checked against a live server by the test suite).

Only what a client reads or writes is spelled out; bigger objects the service describes in
detail (a solve's ``Summary``, solver options) are typed loosely as ``Dict[str, Any]``.

At run time these are plain dicts: nothing is validated on the client side.
"""

from __future__ import annotations

from typing import Any, Dict, List, Literal, Optional, TypedDict

JsonDict = Dict[str, Any]
#: A solve's Summary (``summary.schema.json``): final_chi2, iterations, solve_seconds, ...
Summary = Dict[str, Any]
#: Solver options (``solver-options.schema.json``): method, max_iterations, tolerances, ...
SolverOptions = Dict[str, Any]

VariableKind = Literal["se2", "se3", "point2", "point3", "snavely_camera", "nav_state"]
SessionKind = Literal["pose_graph_2d", "pose_graph_3d", "bundle_adjustment", "sliding_window"]
ExportFormat = Literal["json", "tum", "kitti", "g2o", "ply"]


# ---------------------------------------------------------------- requests
class RobustKernel(TypedDict):
    """``common.schema.json#/$defs/robust_kernel``: ``huber``, ``cauchy``, ``tukey``,
    ``geman_mcclure`` with ``scale`` (delta, in units of whitened error)."""

    kind: str
    scale: float


class _VariableSpecKeys(TypedDict):
    key: int
    kind: str


class VariableSpec(_VariableSpecKeys, total=False):
    """A new variable of a batch (``batch.schema.json#/$defs/variable_spec``). ``value`` absent
    or ``None``: predicted by the server from an odometry factor of the same batch."""

    value: Optional[List[float]]
    fixed: bool
    stamp: float  # seconds on the robot's clock; used by trajectory exports (TUM)


class _FactorSpecKeys(TypedDict):
    type: str
    keys: List[int]
    measurement: List[float]


class FactorSpec(_FactorSpecKeys, total=False):
    """A factor of a batch (``factors.schema.json``): ``information`` (d*d row-major or the
    d(d+1)/2 upper triangle, g2o's order) or ``sigmas`` (d numbers), one of the two."""

    information: List[float]
    sigmas: List[float]
    robust: Optional[RobustKernel]


class GuessSpec(TypedDict):
    key: int
    value: List[float]


class Batch(TypedDict, total=False):
    """``batch.schema.json``: one atomic update of a session (every list optional)."""

    variables: List[VariableSpec]
    factors: List[FactorSpec]
    remove_factors: List[int]
    fix: List[int]
    unfix: List[int]
    guesses: List[GuessSpec]
    producer: Optional[str]
    producer_seq: Optional[int]


class AutoOptimize(TypedDict, total=False):
    """``auto-optimize.schema.json``: ``policy`` plus ``factors`` or ``milliseconds``."""

    policy: str
    factors: int
    milliseconds: int


class FusionBatch(TypedDict):
    """``fusion.schema.json``: messages for a ``sliding_window`` session (``start``, ``imu``,
    ``keyframe``, ``preintegrated_keyframe``, ``relative_pose``, ``pose_prior``,
    ``position_prior``), each a dict with its ``type``."""

    messages: List[JsonDict]


# ---------------------------------------------------------------- answers
class _BatchAckKeys(TypedDict):
    session: str
    sequence: int
    factor_ids: List[int]
    predicted: List[int]
    reflected: bool


class BatchAck(_BatchAckKeys, total=False):
    """``batch-ack.schema.json``; ``solved`` with ``wait`` (and, in a session with a latency
    budget, ``exact``: false for a provisional answer, ``exact_sequence``); the producer fields
    for stamped batches (``duplicate``: a repeat that applied nothing)."""

    solved: bool
    exact: bool
    exact_sequence: int
    producer: str
    producer_seq: int
    accepted_through: int
    duplicate: bool


class _VariableValueKeys(TypedDict):
    key: int
    kind: str
    value: List[float]
    changed: int


class VariableValue(_VariableValueKeys, total=False):
    stamp: float


class Estimate(TypedDict):
    """``estimate.schema.json``."""

    session: str
    sequence: int
    variables: List[VariableValue]


class Export(TypedDict):
    """The estimate as a file (``estimate?format=tum|kitti|g2o|ply``) in rpc answers."""

    session: str
    format: str
    file_name: str
    body: str


class _ErrorBodyKeys(TypedDict):
    code: str
    message: str
    status: int


class ErrorBody(_ErrorBodyKeys, total=False):
    """``common.schema.json#/$defs/error_body`` (under ``error`` in error answers)."""

    field: str
    retry_after: int


class Health(TypedDict):
    status: str
    version: str
    workers: int
    busy_workers: int
    queued: int
    sessions: int
    session_kinds: List[str]
    uptime_seconds: float


class _SessionInfoKeys(TypedDict):
    session: str
    kind: str
    options: SolverOptions
    auto_optimize: AutoOptimize


class SessionInfo(_SessionInfoKeys, total=False):
    """``session-info.schema.json``: what ``create_session`` and ``list_sessions`` answer."""

    factor_types: List[str]
    instance: str  # in a fleet: the owning instance's id
    ros2: Dict[str, Any]  # the ROS 2 binding, defaults filled in (ros2-binding.schema.json)
    max_update_ms: int  # the latency budget (docs/guide/latency.md)


class SessionList(TypedDict):
    sessions: List[SessionInfo]


class _SessionStatsKeys(TypedDict):
    session: str
    kind: str
    sequence: int
    solved_sequence: int
    num_variables: int
    num_factors: int
    pending_batches: int
    solving: bool
    solves: int
    skipped_solves: int
    chi2: Optional[float]
    converged: bool
    auto_optimize: AutoOptimize
    options: SolverOptions
    last_error: Optional[str]
    last_summary: Optional[Summary]
    recovering: bool
    corrupt: bool
    memory_bytes: int


class SessionStats(_SessionStatsKeys, total=False):
    """``session-stats.schema.json`` (``GET /v1/sessions/{session}``)."""

    factor_types: List[str]
    instance: str  # in a fleet: the owning instance's id
    ros2: Dict[str, Any]  # the ROS 2 binding, defaults filled in (ros2-binding.schema.json)
    latency: Dict[str, Any]  # with a latency budget: provisional answers and corrections


class ProducerStatus(TypedDict):
    session: str
    producer: str
    accepted_through: int
    sequence: int
    reflected_sequence: int


class ProducerList(TypedDict):
    """``list_producers`` (``GET /v1/sessions/{session}/producers``): every producer that sent
    the session a numbered batch, by id."""

    session: str
    producers: List[ProducerStatus]


class _MarginalKeys(TypedDict):
    key: int
    kind: str
    fixed: bool
    covariance: List[List[float]]


class Marginal(_MarginalKeys, total=False):
    """One variable's; ``position_covariance`` (3×3, world frame) for kinds with a position."""

    position_covariance: List[List[float]]


class _MarginalsKeys(TypedDict):
    session: str
    sequence: int
    solves: int
    variables: List[Marginal]
    gauge_fixed: List[int]
    reused_factorization: bool
    factorize_seconds: float
    seconds: float


class Marginals(_MarginalsKeys, total=False):
    """``marginals.schema.json``; ``joint`` only when asked for."""

    joint: List[List[float]]


class DrawnVariable(TypedDict):
    key: int
    position: List[float]
    initial: List[float]


class _GraphKeys(TypedDict):
    session: str
    kind: str
    sequence: int
    dimension: int
    poses: List[DrawnVariable]
    points: List[DrawnVariable]
    edges: List[List[int]]


class Graph(_GraphKeys, total=False):
    """``graph.schema.json``: what the web view draws; ``edge_chi2`` (each edge's χ², ``None``
    while a solve holds the problem) absent for sliding windows."""

    edge_chi2: List[Optional[float]]


class OutliersReport(TypedDict):
    """A job's ``outliers`` (``outliers=auto``): the loop closures graduated non-convexity
    rejected."""

    kernel: str
    confidence: float
    candidates: int
    graduated: bool
    outer_iterations: int
    rejected: List[int]
    rejected_labels: List[str]
    least_squares_chi2: float
    seconds: float


class _JobResultKeys(TypedDict):
    summary: Summary
    estimate: JsonDict


class JobResult(_JobResultKeys, total=False):
    """``job-result.schema.json``: a batch job's Summary and optimised estimate; with
    ``outliers=auto`` on a pose graph with loop closures, the ``outliers`` report."""

    outliers: OutliersReport


class _OptimizeAnswerKeys(TypedDict):
    session: str
    sequence: int


class OptimizeAnswer(_OptimizeAnswerKeys, total=False):
    """``optimize``'s answer; with ``wait`` also the statistics after the solve."""

    stats: SessionStats


__all__ = [
    "AutoOptimize", "Batch", "BatchAck", "DrawnVariable", "ErrorBody", "Estimate", "Export",
    "ExportFormat", "FactorSpec", "FusionBatch", "Graph", "GuessSpec", "Health", "JobResult",
    "JsonDict", "Marginal", "OutliersReport", "Marginals", "OptimizeAnswer", "ProducerList", "ProducerStatus",
    "RobustKernel", "SessionInfo", "SessionKind", "SessionList", "SessionStats", "SolverOptions",
    "Summary", "VariableKind", "VariableSpec", "VariableValue",
]
