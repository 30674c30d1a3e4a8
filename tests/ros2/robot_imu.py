"""A ROS 2 robot with an IMU and wheel odometry, as rmw_zenoh puts them on the wire, against a
factord `sliding_window` session bound to its topics (see robot_odometry.py for the wire format).

The robot drives a circle of radius 5 m at 1 m/s: its IMU reads a constant specific force
(0, v²/r, g) and yaw rate v/r in the body frame, at 200 Hz; odometry at 20 Hz gives the true
pose. Odometry is published 50 ms ahead of the IMU (it often is: wheel encoders are read before
the IMU's samples are delivered), so keyframes must wait for the IMU to cover them. Checks:

1. kinds: a pose_graph_3d refuses an IMU topic, a sliding_window needs one (400 at the field);
2. factord's node subscribes to the IMU (liveliness token with sensor_msgs/Imu's type hash);
3. the published nav_msgs/Path holds every keyframe (lag-smoothed, then the window) at its
   odometry stamp, within 2 cm and 0.01 rad of the circle, and the pose output carries a
   positive definite covariance;
4. an IMU sample out of order and an undecodable one are reported at `ros2.imu_topic` and
   change nothing.
"""

import argparse
import json
import math
import threading
import time
import urllib.error

import numpy as np

from robot_odometry import (DOMAIN, ODOM, PATH, PWCS, STORE, Robot, collector, dds_name, header,
                            http, odometry, ros_graph, topic_key, wait_for, zenoh_session)

IMU = "sensor_msgs/msg/Imu"
RADIUS, SPEED, G = 5.0, 1.0, 9.81
OMEGA = SPEED / RADIUS
T0 = 1_700_000_100.0
DURATION = 15.0
ODOMETRY_LEAD = 0.05


def truth(t):
    """(x, y, yaw) on the circle at `t` seconds after T0, heading along it."""
    angle = OMEGA * t
    return RADIUS * math.cos(angle), RADIUS * math.sin(angle), angle + math.pi / 2


def imu(stamp):
    t = STORE.types
    vector = t["geometry_msgs/msg/Vector3"]
    message = t[IMU](
        header=header(stamp, "imu_link"),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([-1.0] + [0.0] * 8),  # REP 145: no orientation
        angular_velocity=vector(x=0.0, y=0.0, z=OMEGA),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector(x=0.0, y=SPEED * SPEED / RADIUS, z=G),
        linear_acceleration_covariance=np.zeros(9))
    return bytes(STORE.serialize_cdr(message, IMU))


def refused(base, body):
    try:
        http(base, "POST", "/v1/sessions", body)
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())["error"]
    raise AssertionError(f"created: {body}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--http", required=True)
    parser.add_argument("--zenoh", required=True)
    args = parser.parse_args()
    binding = {
        "domain_id": DOMAIN, "odometry_topic": "/robot2/odom", "imu_topic": "/robot2/imu",
        "path_topic": "/robot2/factord/path", "pose_topic": "/robot2/factord/pose",
        "window": 5, "keyframe_distance": 1.0, "keyframe_angle": 0.5,
    }
    # 1. Which kinds take which topics.
    status, error = refused(args.http, {"session": "g", "kind": "pose_graph_3d", "ros2": binding})
    assert (status, error["code"], error["field"]) == (400, "invalid_value", "ros2.imu_topic"), error
    no_imu = {k: v for k, v in binding.items() if k != "imu_topic"}
    status, error = refused(args.http, {"session": "w", "kind": "sliding_window", "ros2": no_imu})
    assert (status, error["field"]) == (400, "ros2.imu_topic"), error
    print("kinds:", error["message"])
    http(args.http, "POST", "/v1/sessions",
         {"session": "ros_imu", "kind": "sliding_window", "ros2": binding})

    with zenoh_session(args.zenoh) as session:  # closed however run() ends
        run(session, args)


def run(session, args):
    # 2. The IMU subscription in the ROS graph.
    def imu_token():
        return [t for t in ros_graph(session) if "/factord_ros_imu/%robot2%imu/" in t]
    token = wait_for("the IMU subscription's token", imu_token)[0]
    assert token.split("/")[5] == "MS" and token.endswith(
        f"/{dds_name(IMU)}/{STORE.hash_rihs01(IMU)}/::,10:,:,:,,"), token
    print("imu subscription:", token)
    print("imu key:", topic_key("/robot2/imu", IMU))

    received = {"path": [], "pose": [], "errors": []}
    lock = threading.Lock()

    keep, errors = collector(received, lock)
    subscribers = [
        session.declare_subscriber(topic_key("/robot2/factord/path", PATH), keep("path", PATH)),
        session.declare_subscriber(topic_key("/robot2/factord/pose", PWCS), keep("pose", PWCS)),
        session.declare_subscriber("factord/ros_imu/out/errors", errors())]
    robot = Robot(session, (("/robot2/odom", ODOM), ("/robot2/imu", IMU)))
    time.sleep(0.5)

    # 3. Drive: odometry every 10th IMU sample, 50 ms ahead of it.
    odometry_stamps = []
    steps = int(DURATION * 200)
    for i in range(steps + 1):
        t = i / 200
        if i % 10 == 0:
            x, y, yaw = truth(t + ODOMETRY_LEAD)
            stamp = T0 + t + ODOMETRY_LEAD
            robot.publish("/robot2/odom", odometry(stamp, x, y, yaw, SPEED))
            odometry_stamps.append(stamp)
        robot.publish("/robot2/imu", imu(T0 + t))
        if i % 20 == 0:
            time.sleep(0.002)
    last_imu = T0 + steps / 200
    # The keyframes factord makes: by the thresholds, once the IMU covers them.
    kept, reference = [], None
    for stamp in odometry_stamps:
        x, y, yaw = truth(stamp - T0)
        if reference is None or math.hypot(x - reference[0], y - reference[1]) >= 1.0 or \
                abs(math.remainder(yaw - reference[2], 2 * math.pi)) >= 0.5:
            reference = (x, y, yaw)
            kept.append(stamp)
    kept = [s for s in kept if s <= last_imu]

    def full_path():
        with lock:
            if received["path"] and len(received["path"][-1].poses) == len(kept):
                return received["path"][-1]
        return None
    try:
        path = wait_for(f"a path of {len(kept)} keyframes", full_path)
    except AssertionError:
        with lock:
            print("paths:", [len(p.poses) for p in received["path"]], "errors:",
                  received["errors"])
        raise
    worst_position = worst_yaw = 0.0
    for pose, stamp in zip(path.poses, kept):
        got = pose.header.stamp.sec + pose.header.stamp.nanosec * 1e-9
        assert abs(got - stamp) < 1e-6, (got, stamp)
        x, y, yaw = truth(stamp - T0)
        p, q = pose.pose.position, pose.pose.orientation
        worst_position = max(worst_position, math.hypot(p.x - x, p.y - y), abs(p.z))
        got_yaw = 2 * math.atan2(q.z, q.w)
        worst_yaw = max(worst_yaw, abs(math.remainder(got_yaw - yaw, 2 * math.pi)))
    assert worst_position < 0.02 and worst_yaw < 0.01, (worst_position, worst_yaw)
    print(f"path: {len(path.poses)} keyframes from {steps + 1} IMU samples and "
          f"{len(odometry_stamps)} odometry messages; worst {worst_position * 1000:.3f} mm, "
          f"{worst_yaw:.2e} rad off the circle")
    pose = wait_for("a pose output", lambda: received["pose"][-1] if received["pose"] else None)
    cov = np.array(pose.pose.covariance).reshape(6, 6)
    assert np.all(np.linalg.eigvalsh((cov + cov.T) / 2) > 0), cov
    print(f"pose: sigma_x {math.sqrt(cov[0, 0]) * 100:.2f} cm")

    # 4. Bad IMU input is reported at its topic.
    robot.publish("/robot2/imu", imu(T0 + 1.0))
    robot.publish("/robot2/imu", b"\x00\x01\x00\x00garbage")

    def imu_errors():
        with lock:
            errors = [e for e in received["errors"]
                      if e["error"]["code"] == "ros2_bad_message"
                      and e["error"]["field"] == "ros2.imu_topic"]
        return errors if len(errors) >= 2 else None
    for e in wait_for("two IMU refusals", imu_errors):
        print("error event:", e["error"]["message"])
    state = http(args.http, "GET", "/v1/sessions/ros_imu")  # the refusals reached no window
    assert state.get("last_error") is None, state
    for subscriber in subscribers:
        subscriber.undeclare()
    print("ros2 imu robot: ok")


if __name__ == "__main__":
    main()
