"""factord in process, with GTSAM's Python names: a GTSAM script ports by ``import factord as gtsam``
for the part of the API covered here (see clients/python/native/README.md for the table).

Poses are ``Pose2``/``Pose3`` objects, points are numpy arrays (as in GTSAM 4), keys are ints
(``symbol('x', 1)`` or ``X(1)`` from ``symbol_shorthand``). Everything heavy (building the problem,
solving, marginals, the incremental engine) runs in the factord library, in this process.
"""

import numpy as _np

from . import _native
from ._native import (  # noqa: F401  (re-exported)
    BearingFactor2D,
    BearingRangeFactor2D,
    BetweenFactorPose2,
    BetweenFactorPoint2,
    BetweenFactorPoint3,
    BetweenFactorPose3,
    CustomFactor,
    DimensionMismatch,
    DoglegOptimizer,
    DoglegParams,
    FactordError,
    GaussNewtonOptimizer,
    GPSFactor,
    GPSFactorArm,
    GaussNewtonParams,
    IndeterminantLinearSystemException,
    InvalidNoiseModel,
    ISAM2,
    ISAM2Params,
    ISAM2Result,
    JointMarginal,
    LevenbergMarquardtOptimizer,
    SnavelyCamera,
    SnavelyReprojectionFactor,
    LevenbergMarquardtParams,
    Marginals,
    NonlinearFactor,
    NonlinearFactorGraph,
    NonlinearOptimizerParams,
    Pose2,
    Pose3,
    PoseToPointFactor3D,
    PriorFactorPoint2,
    PriorFactorPoint3,
    PriorFactorPose2,
    PriorFactorPose3,
    RangeFactor2D,
    RangeFactor3D,
    RangeFactorPose2,
    RangeFactorPose3,
    Rot2,
    Rot3,
    Values,
    ValuesIncorrectType,
    ValuesKeyAlreadyExists,
    ValuesKeyDoesNotExist,
    keyName,
    loadBal,
    readG2o,
    solve,
    symbol,
    symbolChr,
    symbolIndex,
    writeG2o,
)

from . import expressions  # noqa: E402
from .expressions import FactorType  # noqa: E402,F401
from .session import IncrementalSession, Service, ServiceError  # noqa: E402,F401

__all__ = [name for name in dir() if not name.startswith("_")] + [
    "Point2",
    "Point3",
    "noiseModel",
    "symbol_shorthand",
    "utilities",
]


def Point2(x=0.0, y=0.0):
    """A 2D point: a numpy array, as GTSAM 4's ``Point2``."""
    return _np.array([x, y], dtype=float)


def Point3(x=0.0, y=0.0, z=0.0):
    """A 3D point: a numpy array, as GTSAM 4's ``Point3``."""
    return _np.array([x, y, z], dtype=float)


class _Namespace:
    """A class used only as a namespace (``noiseModel.Diagonal.Sigmas``)."""

    def __init__(self, **members):
        self.__dict__.update(members)


def _robust(m_estimator, base):
    return _native.NoiseModel.robust(m_estimator, base)


def _estimator(kind):
    return _Namespace(Create=lambda k: _native.MEstimator(kind, float(k)))


noiseModel = _Namespace(
    Base=_native.NoiseModel,
    Diagonal=_Namespace(
        Sigmas=_native.NoiseModel.diagonal_sigmas,
        Variances=_native.NoiseModel.diagonal_variances,
        Precisions=_native.NoiseModel.diagonal_precisions,
    ),
    Isotropic=_Namespace(
        Sigma=_native.NoiseModel.isotropic_sigma,
        Variance=_native.NoiseModel.isotropic_variance,
        Precision=_native.NoiseModel.isotropic_precision,
    ),
    Unit=_Namespace(Create=_native.NoiseModel.unit),
    Gaussian=_Namespace(
        Covariance=_native.NoiseModel.gaussian_covariance,
        Information=_native.NoiseModel.gaussian_information,
        SqrtInformation=_native.NoiseModel.gaussian_sqrt_information,
    ),
    Robust=_Namespace(Create=_robust),
    mEstimator=_Namespace(
        Base=_native.MEstimator,
        Huber=_estimator("huber"),
        Cauchy=_estimator("cauchy"),
        Tukey=_estimator("tukey"),
        GemanMcClure=_estimator("geman_mcclure"),
    ),
)


from . import symbol_shorthand  # noqa: E402  (gtsam.symbol_shorthand)


def _extract_pose2(values):
    """N×3 array of (x, y, θ) of every Pose2, in key order (GTSAM: utilities.extractPose2)."""
    return values._pose2_rows()[1].reshape(-1, 3)


def _extract_pose3(values):
    """N×12 array (R row-major, then t) of every Pose3 (GTSAM: utilities.extractPose3)."""
    return values._pose3_rows()[1].reshape(-1, 12)


def _extract_point2(values):
    return values._point_rows(2)[1].reshape(-1, 2)


def _extract_point3(values):
    return values._point_rows(3)[1].reshape(-1, 3)


def _all_pose2(values):
    """(keys, N×3 array): the poses with the keys they are under (factord's)."""
    keys, rows = values._pose2_rows()
    return keys, rows.reshape(-1, 3)


utilities = _Namespace(
    extractPose2=_extract_pose2,
    extractPose3=_extract_pose3,
    extractPoint2=_extract_point2,
    extractPoint3=_extract_point3,
    allPose2=_all_pose2,
)
