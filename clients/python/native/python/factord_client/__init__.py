"""Python client for factord: HTTP (:class:`HttpClient`) and zenoh (:class:`ZenohClient`, needs
``eclipse-zenoh``), numpy in and out (:class:`Batch` builds batches from arrays,
``estimate_array`` reads poses back as an (N, 3) / (N, 7) array), poses and noise models
(:class:`Pose2`, :class:`Pose3`, :class:`Noise`), the wire shapes as TypedDicts
(:mod:`factord_client.wire`), and a small g2o reader (:mod:`factord_client.g2o`).

Every failure raises :class:`FactordError` or a subclass (service errors, unreachable service,
client-side timeouts, refused producer batches), carrying ``status``, ``code`` and ``field``."""

from .batch import Batch, EstimateArray, dumps, jsonable
from .errors import BatchRefused, FactordConnectionError, FactordError, FactordTimeout
from .geometry import Noise, Pose2, Pose3, pose_from_wire
from .http import EventStream, HttpClient
from .poses_binary import PosesBinaryError, decode_poses
from .producer import HttpProducer
from .robots import Robot, robot_id, robot_key, robot_of_key

__all__ = [
    "Batch",
    "BatchRefused",
    "EstimateArray",
    "EventStream",
    "FactordConnectionError",
    "FactordError",
    "FactordTimeout",
    "HttpClient",
    "HttpProducer",
    "Noise",
    "Pose2",
    "Pose3",
    "PosesBinaryError",
    "Robot",
    "robot_id",
    "StreamProducer",
    "ZenohClient",
    "decode_poses",
    "dumps",
    "jsonable",
    "pose_from_wire",
    "robot_key",
    "robot_of_key",
]
__version__ = "0.2.0"


def __getattr__(name: str):  # lazy: importing the package must not need zenoh
    if name == "ZenohClient":
        from .zenoh_client import ZenohClient

        return ZenohClient
    if name == "StreamProducer":
        from .stream_producer import StreamProducer

        return StreamProducer
    raise AttributeError(name)
