"""Robots in one session (a session created with ``robots``, docs/guide/many-robots.md): keys
named like GTSAM's ``Symbol`` (``robot_key('b', 5)`` is pose 5 of robot ``b``), and a
:class:`Robot` handle that reads one robot's trajectory back in the map or its own frame."""

from typing import Any, Dict, Optional

from .geometry import AnyPose, pose_from_wire

_INDEX_BITS = 56


def robot_key(robot: str, index: int) -> int:
    """The key of pose ``index`` of ``robot`` (one printable ASCII character): ``(c << 56) | i``,
    GTSAM's ``Symbol(c, i)``."""
    if len(robot) != 1 or not (0x21 <= ord(robot) <= 0x7E):
        raise ValueError(f"robot {robot!r} is not one printable ASCII character")
    if not 0 <= index < (1 << _INDEX_BITS):
        raise ValueError(f"pose index {index} is outside 0..2^56")
    return (ord(robot) << _INDEX_BITS) | index


def robot_of_key(key: int) -> Optional[str]:
    """The robot ``key`` names, or ``None`` for a key of no robot."""
    c = key >> _INDEX_BITS
    return chr(c) if 0x21 <= c <= 0x7E else None


def robot_id(robot: str) -> str:
    """How ``robot`` is named in key expressions (``<prefix>/<session>/robot/<id>/…``) and on
    ROS 2 ``/tf`` (``robot_<id>/odom``): its character when that is an ASCII letter or digit,
    else ``x`` and its two hex digits (``*`` is ``x2a``)."""
    robot_key(robot, 0)  # checks the name
    return robot if robot.isascii() and robot.isalnum() else f"x{ord(robot):02x}"


class Robot:
    """One robot of a session with robots, over an :class:`HttpClient` (or anything with its
    ``estimate`` and ``robots`` methods)."""

    def __init__(self, client: Any, session: str, robot: str) -> None:
        robot_key(robot, 0)  # checks the name
        self.client = client
        self.session = session
        self.robot = robot

    def key(self, index: int) -> int:
        """The key of this robot's pose ``index``."""
        return robot_key(self.robot, index)

    def poses(self, frame: str = "map") -> Dict[int, AnyPose]:
        """This robot's poses by index, in the map or (``frame="odom"``) its own odometry
        frame."""
        estimate = self.client.estimate(self.session, robot=self.robot, frame=frame)
        mask = (1 << _INDEX_BITS) - 1
        return {v["key"] & mask: pose_from_wire(v["kind"], v["value"])
                for v in estimate["variables"]}

    def status(self) -> Dict[str, Any]:
        """This robot's entry in the session's robots report (its frame, component, whether it
        is in the map)."""
        for r in self.client.robots(self.session)["robots"]:
            if r["robot"] == self.robot:
                return r
        raise KeyError(f"session {self.session} has no robot {self.robot!r} yet")
