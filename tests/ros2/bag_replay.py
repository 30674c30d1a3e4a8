"""Replays a ROS 2 bag into a factord session bound to its odometry topic, as `ros2 bag play`
over rmw_zenoh would: each recorded CDR message is put unchanged on the rmw_zenoh key with the
attachment, and the published nav_msgs/Path is checked against the poses the bag was made from.

The bag is written here with rosbags (rosbag2, MCAP storage, Jazzy types) from a 3D pose graph's
vertices (the first N poses of a g2o file, 10 Hz stamps): a trajectory whose relative odometry
is consistent, so every pose is a keyframe (thresholds 0) and the optimum is the trajectory.
"""

import argparse
import json
import math
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import zenoh
import zenoh.ext as zext
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
ODOM = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
DOMAIN = 3


def key(topic, msgtype):
    pkg, kind, name = msgtype.split("/")
    return f"{DOMAIN}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/{STORE.hash_rihs01(msgtype)}"


def poses_of(g2o, count):
    poses = []
    for line in Path(g2o).read_text().splitlines():
        fields = line.split()
        if fields and fields[0] == "VERTEX_SE3:QUAT":
            poses.append([float(v) for v in fields[2:9]])
            if len(poses) == count:
                break
    return poses


def write_bag(path, poses, start):
    t = STORE.types
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/odom", ODOM, typestore=STORE)
        for i, (x, y, z, qx, qy, qz, qw) in enumerate(poses):
            stamp_ns = start + i * 100_000_000
            message = t[ODOM](
                header=t["std_msgs/msg/Header"](
                    stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                           nanosec=stamp_ns % 10**9),
                    frame_id="odom"),
                child_frame_id="base_link",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](
                    pose=t["geometry_msgs/msg/Pose"](
                        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
                    covariance=np.diag([0.01] * 3 + [0.001] * 3).reshape(36)),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](
                    twist=t["geometry_msgs/msg/Twist"](
                        linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36)))
            writer.write(connection, stamp_ns, bytes(STORE.serialize_cdr(message, ODOM)))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--http", required=True)
    parser.add_argument("--zenoh", required=True)
    parser.add_argument("--g2o", required=True)
    parser.add_argument("--poses", type=int, default=300)
    args = parser.parse_args()

    poses = poses_of(args.g2o, args.poses)
    start = 1_700_000_000 * 10**9
    bag = Path(tempfile.mkdtemp(prefix="factord-ros2-")) / "odometry_bag"
    write_bag(bag, poses, start)

    binding = {"domain_id": DOMAIN, "odometry_topic": "/odom", "path_topic": "/factord/path",
               "keyframe_distance": 0.0, "keyframe_angle": 0.0}
    body = json.dumps({"session": "bag_replay", "kind": "pose_graph_3d", "ros2": binding})
    request = urllib.request.Request(args.http + "/v1/sessions", data=body.encode(),
                                     method="POST", headers={"content-type": "application/json"})
    try:
        urllib.request.urlopen(request, timeout=30).read()
    except urllib.error.HTTPError as e:
        raise AssertionError(f"creating the session: {e.code} {e.read().decode()}") from e

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([args.zenoh]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    try:
        replay(session, bag, poses, start, args.g2o)
    finally:
        session.close()  # an open session's threads would keep a failed run alive


def replay(session, bag, poses, start, g2o):
    latest = {}
    lock = threading.Lock()

    def on_path(sample):
        message = STORE.deserialize_cdr(bytes(sample.payload.to_bytes()), PATH)
        with lock:
            latest["path"] = message
    subscriber = session.declare_subscriber(key("/factord/path", PATH), on_path)
    time.sleep(0.5)

    # Replay: the recorded bytes, unchanged, with rmw_zenoh's attachment.
    gid = bytes(range(16))
    with Reader(bag) as reader:
        assert reader.message_count == len(poses), reader.message_count
        for sequence, (connection, _, rawdata) in enumerate(reader.messages(), 1):
            assert connection.msgtype == ODOM and connection.topic == "/odom"
            attachment = zext.z_serialize((zext.Int64(sequence), zext.Int64(time.time_ns()), gid))
            session.put(key(connection.topic, ODOM), bytes(rawdata), attachment=attachment)
            time.sleep(0.001)

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        with lock:
            path = latest.get("path")
        if path is not None and len(path.poses) == len(poses):
            break
        time.sleep(0.1)
    else:
        raise AssertionError(f"no path of {len(poses)} poses; last had "
                             f"{len(path.poses) if path is not None else 0}")
    worst_t, worst_r = 0.0, 0.0
    for i, (got, want) in enumerate(zip(path.poses, poses)):
        stamp = got.header.stamp.sec * 10**9 + got.header.stamp.nanosec
        assert abs(stamp - (start + i * 100_000_000)) < 1000, (i, stamp)
        p, q = got.pose.position, got.pose.orientation
        worst_t = max(worst_t, math.dist((p.x, p.y, p.z), want[:3]))
        # The file's quaternions have 6 digits: compare with the unit one factord keeps.
        want_q = np.array(want[3:]) / np.linalg.norm(want[3:])
        dot = abs(np.dot([q.x, q.y, q.z, q.w], want_q))
        worst_r = max(worst_r, 2 * math.acos(min(1.0, dot)))
    assert worst_t < 1e-6 and worst_r < 1e-6, (worst_t, worst_r)
    print(f"bag replay: {len(poses)} odometry messages from {Path(g2o).name} via "
          f"{bag.name} (MCAP) -> path of {len(path.poses)} keyframes; max deviation "
          f"{worst_t:.2e} m, {worst_r:.2e} rad")
    subscriber.undeclare()


if __name__ == "__main__":
    main()
