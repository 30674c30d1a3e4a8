"""Two robots over rmw_zenoh in one map, a node per robot namespace (`ros2.robots`), the robots
peers of factord or (`--router`) clients of the zenoh router factord is connected to.

Robots a (`/husky1`) and b (`/husky2`) each publish odometry in their own namespace and their
own odometry frame (b's origin is unknown to factord); a place-recognition front-end publishes
closures between them on `/robot_closures` (`factord_msgs/RobotLoopClosure`, rosbags-encoded
from our .msg file). Checks, in order:

1. the ROS graph has one `factord_<session>` node in each robot's namespace, each subscribed to
   its robot's `odom` and to `/robot_closures` (rosbags' hash of our .msg file);
2. before any closure: a's path (`/husky1/factord/path`) is in `map`; b's
   (`/husky2/factord/path`) is in its own odometry frame `robot_b/odom`, and is its odometry;
   `/tf` has `map → robot_a/odom` and nothing for b;
3. a closure naming no robot of the binding is refused on the error stream, naming the field;
4. three closures between the robots (named by namespace and by id) merge b into the map: b's
   path comes again in `map`, each keyframe where b truly was (within 1e-4 m), `/tf` has
   `map → robot_b/odom` at b's true odometry origin, and `GET …/robots` reports the merge;
5. a closure from a keyframe a has not made yet is held by b's node (no refusal, no factor),
   and enters the session with a's keyframe once a's odometry reaches its stamp.
"""

import argparse
import json
import math
import threading
import time
import urllib.error

import zenoh
from rosbags.typesys import get_types_from_msg

import robot_odometry as ro
from robot_odometry import STORE, http, wait_for, zenoh_session

ODOM, PATH, TF = ro.ODOM, ro.PATH, ro.TF
CLOSURE = "factord_msgs/msg/RobotLoopClosure"
SESSION = "ros_fleet"
# Where b's odometry frame sits in the world (a's odometry frame, the map): unknown to factord.
B_ODOM_ORIGIN = (-5.0, 7.0, 1.0)
# Where b's drive starts in the world.
B_START = (1.0, 1.5, 0.2)


def compose(p, q):
    x, y, yaw = p
    return (x + math.cos(yaw) * q[0] - math.sin(yaw) * q[1],
            y + math.sin(yaw) * q[0] + math.cos(yaw) * q[1], yaw + q[2])


def inverse(p):
    x, y, yaw = p
    return (-math.cos(yaw) * x - math.sin(yaw) * y, math.sin(yaw) * x - math.cos(yaw) * y, -yaw)


def drives():
    """Truth (in the world) and odometry (stamp, x, y, yaw) of both robots: a's odometry frame
    is the world; b drives the same shape from B_START, its odometry in its own frame."""
    shape = ro.trajectory()
    truth_a = shape
    truth_b = [(t + 0.013, *compose(B_START, (x, y, yaw))) for t, x, y, yaw in shape]
    to_b_odom = inverse(B_ODOM_ORIGIN)
    odometry_b = [(t, *compose(to_b_odom, (x, y, yaw))) for t, x, y, yaw in truth_b]
    return truth_a, truth_b, odometry_b


def closure(from_robot, to_robot, from_pose, to_pose, stamp):
    rel = compose(inverse(from_pose[1:]), to_pose[1:])
    sigmas = [0.01] * 3 + [0.002] * 3
    return bytes(STORE.serialize_cdr(STORE.types[CLOSURE](
        header=ro.header(stamp, ""), from_robot=from_robot,
        from_stamp=ro.header(from_pose[0], "").stamp, to_robot=to_robot,
        to_stamp=ro.header(to_pose[0], "").stamp,
        relative_pose=ro.pose_msg(rel[0], rel[1], 0.0, rel[2]),
        covariance=ro.covariance(sigmas), may_be_wrong=False), CLOSURE))


def yaw_of(q):
    return 2.0 * math.atan2(q.z, q.w)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--http", required=True)
    parser.add_argument("--zenoh", required=True)
    parser.add_argument("--router", help="connect to this zenoh router as a client instead")
    args = parser.parse_args()
    with open("clients/ros2/factord_msgs/msg/RobotLoopClosure.msg") as f:
        STORE.register(get_types_from_msg(f.read(), CLOSURE))
    binding = {
        "domain_id": ro.DOMAIN, "odometry_topic": "odom", "path_topic": "factord/path",
        "pose_topic": "factord/pose", "tf_topic": "/tf",
        "robot_loop_closure_topic": "/robot_closures",
        "robots": {"a": "/husky1", "b": "/husky2"},
        # Off the 0.1 m steps, so that rounding in b's frame cannot move a keyframe.
        "keyframe_distance": 1.05, "keyframe_angle": 0.5,
    }
    # A node per robot needs a session with robots.
    try:
        http(args.http, "POST", "/v1/sessions",
             {"session": "no_robots", "kind": "pose_graph_3d", "ros2": binding})
        raise AssertionError("a node per robot in a session without robots was accepted")
    except urllib.error.HTTPError as e:
        body = json.loads(e.read())
        assert e.code == 400 and body["error"]["field"] == "ros2.robots", (e.code, body)
    created = http(args.http, "POST", "/v1/sessions",
                   {"session": SESSION, "kind": "pose_graph_3d", "ros2": binding,
                    "robots": {"min_closures": 3}})
    assert created["ros2"]["robots"] == binding["robots"], created
    with robots_session(args) as session:
        run(session, args.http)


def robots_session(args):
    """A peer of factord, or a client of the router factord is connected to (rmw_zenoh's
    deployment: every node a client of the robot's router)."""
    if args.router is None:
        return zenoh_session(args.zenoh)
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.router]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def run(session, base):
    # 1. A node per namespace, subscribed to its robot's odometry and to the closures.
    def graph():
        ours = [t for t in ro.ros_graph(session) if f"/factord_{SESSION}" in t]
        nodes = [t for t in ours if "/NN/" in t]
        return ours if len(nodes) == 2 else None
    tokens = wait_for("both robots' nodes", graph)
    for namespace in ("%husky1", "%husky2"):
        node = [t for t in tokens if "/NN/" in t and t.endswith(f"/%/{namespace}/factord_{SESSION}")]
        assert node, f"no node in {namespace}: {tokens}"
        odom = f"{namespace}%odom/{ro.dds_name(ODOM)}/"
        closures = f"/%robot_closures/{ro.dds_name(CLOSURE)}/{STORE.hash_rihs01(CLOSURE)}/"
        mine = [t for t in tokens if f"/{namespace}/factord_{SESSION}/" in t and "/MS/" in t]
        assert any(odom in t for t in mine), f"{namespace}: no odometry subscription in {mine}"
        assert any(closures in t for t in mine), f"{namespace}: no closure subscription in {mine}"
        print("node:", node[0])
    print(f"{CLOSURE}: {STORE.hash_rihs01(CLOSURE)}")

    received = {"a": [], "b": [], "tf": [], "errors": []}
    lock = threading.Lock()

    on, errors = ro.collector(received, lock)
    subscribers = [
        session.declare_subscriber(ro.topic_key("/husky1/factord/path", PATH), on("a", PATH)),
        session.declare_subscriber(ro.topic_key("/husky2/factord/path", PATH), on("b", PATH)),
        session.declare_subscriber(ro.topic_key("/tf", TF), on("tf", TF)),
        session.declare_subscriber(f"factord/{SESSION}/out/errors", errors()),
    ]
    robots = ro.Robot(session, topics=(("/husky1/odom", ODOM), ("/husky2/odom", ODOM),
                                       ("/robot_closures", CLOSURE)))

    # 2. Both robots drive, interleaved; each keyframed in its own key space and frame.
    truth_a, truth_b, odometry_b = drives()
    # The map is the frame of the robot seen first: a's, once its first keyframe is in.
    robots.publish("/husky1/odom", ro.odometry(*truth_a[0]))
    wait_for("a's first keyframe", lambda: received["a"])
    robots.publish("/husky2/odom", ro.odometry(*odometry_b[0]))
    for a, b in zip(truth_a[1:], odometry_b[1:]):
        robots.publish("/husky1/odom", ro.odometry(*a))
        robots.publish("/husky2/odom", ro.odometry(*b))
    kept_a = ro.keyframes(truth_a, 1.05, 0.5)
    kept_b = ro.keyframes(odometry_b, 1.05, 0.5)

    def newest(name, predicate, what):
        def check():
            with lock:
                if received[name] and predicate(received[name][-1]):
                    return received[name][-1]
            return None
        return wait_for(what, check)
    path_a = newest("a", lambda p: len(p.poses) == len(kept_a), "a's whole path")
    path_b = newest("b", lambda p: len(p.poses) == len(kept_b), "b's whole path")
    assert path_a.header.frame_id == "map", path_a.header
    assert path_b.header.frame_id == "robot_b/odom", path_b.header
    for pose, (t, x, y, yaw) in zip(path_b.poses, kept_b):
        p = pose.pose.position
        assert abs(ro.stamp_of(pose.header) - t) < 1e-6, (pose.header, t)
        assert math.hypot(p.x - x, p.y - y) < 1e-6, (p, x, y)
    with lock:
        children = {t.child_frame_id for m in received["tf"] for t in m.transforms}
    assert children == {"robot_a/odom"}, children
    print(f"before the merge: a's path {len(path_a.poses)} keyframes in map, b's "
          f"{len(path_b.poses)} in robot_b/odom (its odometry); /tf children {sorted(children)}")

    # 3. A closure to no robot of the binding: refused, the field named.
    robots.publish("/robot_closures", closure("/husky1", "/husky9", kept_a[5], kept_b[5], 1.0))
    def refusals():
        with lock:
            errors = [e["error"] for e in received["errors"]]
        return [e for e in errors if "husky9" in e["message"]]
    refused = wait_for("the refusal of a closure to /husky9", refusals)
    assert refused[0]["field"] == "ros2.robot_loop_closure_topic", refused
    assert refused[0]["code"] == "ros2_bad_message", refused
    print("refused:", refused[0]["message"])

    # 4. Three closures between the robots, where their drives cross.
    truth_at = {round(s[0], 6): s for s in truth_b}
    pairs = [(3, 2), (10, 9), (16, 14)]
    for n, (i, j) in enumerate(pairs):
        names = ("/husky1", "husky2") if n != 1 else ("a", "b")
        b_truth = truth_at[round(kept_b[j][0], 6)]
        robots.publish("/robot_closures", closure(*names, kept_a[i], b_truth, 2.0 + n))

    def b_in_map(p):
        return p.header.frame_id == "map" and len(p.poses) == len(kept_b)
    path_b = newest("b", b_in_map, "b's path in the map after the merge")
    worst = 0.0
    for pose, kept in zip(path_b.poses, kept_b):
        _, x, y, yaw = truth_at[round(ro.stamp_of(pose.header), 6)]
        p = pose.pose.position
        worst = max(worst, math.hypot(p.x - x, p.y - y), abs(math.remainder(
            yaw_of(pose.pose.orientation) - yaw, math.tau)))
    assert worst < 1e-4, f"b's keyframes are up to {worst} from where b was"
    report = http(base, "GET", f"/v1/sessions/{SESSION}/robots")
    assert len(report["merges"]) == 1, report

    def b_frame():
        with lock:
            frames = [t for m in received["tf"] for t in m.transforms
                      if t.child_frame_id == "robot_b/odom"]
        return frames[-1] if frames else None
    frame = wait_for("map → robot_b/odom on /tf", b_frame)
    assert frame.header.frame_id == "map", frame.header
    t, q = frame.transform.translation, frame.transform.rotation
    off = max(math.hypot(t.x - B_ODOM_ORIGIN[0], t.y - B_ODOM_ORIGIN[1]),
              abs(math.remainder(yaw_of(q) - B_ODOM_ORIGIN[2], math.tau)))
    assert off < 1e-4, (t, q, B_ODOM_ORIGIN)
    print(f"after the merge: b's {len(path_b.poses)} keyframes in map within {worst:.2e} of the "
          f"truth; map → robot_b/odom within {off:.2e} of b's odometry origin")

    # 5. A closure from a keyframe a has not made yet (a's odometry lags place recognition):
    # b's node holds it, and takes it once a's odometry makes that keyframe.
    last = truth_a[-1]
    ahead = (last[0] + 2.0, *compose(last[1:], (3.0, 0.0, 0.1)))
    b_seen = truth_at[round(kept_b[len(kept_b) // 2][0], 6)]

    def factors():
        return http(base, "GET", f"/v1/sessions/{SESSION}")["num_factors"]
    before = factors()
    with lock:
        errors_before = len(received["errors"])
    robots.publish("/robot_closures", closure("a", "b", ahead, b_seen, 10.0))
    time.sleep(1.0)  # a refusal comes within milliseconds
    with lock:
        refusals = [e["error"] for e in received["errors"][errors_before:]]
    assert not refusals, f"a closure ahead of a's odometry was refused: {refusals}"
    assert factors() == before, "the closure entered before a's keyframe"
    robots.publish("/husky1/odom", ro.odometry(*ahead))
    wait_for("the held closure, with a's new keyframe", lambda: factors() == before + 2 or None)
    print("a closure ahead of a's odometry was held, then taken with a's keyframe")
    for s in subscribers:
        s.undeclare()


if __name__ == "__main__":
    main()
