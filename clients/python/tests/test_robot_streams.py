"""A robot's own zenoh keys through the Python client (issue 54 item 4): two robots in their own
frames merge on three closures; robot b follows its trajectory in its odometry frame on
``subscribe_robot_poses`` (JSON and binary) and its place in the map on
``subscribe_robot_frame``, and reads both back from its queryables. Run against a server:
``python test_robot_streams.py --http http://127.0.0.1:8080 --zenoh tcp/127.0.0.1:7447``."""

import argparse
import math
import sys
import threading
import time

from harness import Checks, expect

from factord_client import HttpClient, ZenohClient, robot_id, robot_key, robot_of_key

INFO = [400.0, 0.0, 0.0, 400.0, 0.0, 2500.0]


def walk(offset, poses):
    """A walk around a 10 m square, ``offset`` poses in (1 m apart)."""
    out = []
    for i in range(poses):
        s = (i + offset) % 40
        side, along = s // 10, float(s % 10)
        out.append([(along, 0.0, 0.0), (10.0, along, math.pi / 2),
                    (10.0 - along, 10.0, math.pi), (0.0, 10.0 - along, -math.pi / 2)][side])
    return out


def between(a, b):
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    dt = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
    return [c * dx + s * dy, -s * dx + c * dy, dt]


def robot_batch(r, world, poses):
    origin = world[0]
    variables = [{"key": robot_key(r, i), "kind": "se2", "value": between(origin, world[i])}
                 for i in poses]
    factors = [{"type": "between_se2", "keys": [robot_key(r, i - 1), robot_key(r, i)],
                "measurement": between(world[i - 1], world[i]), "information": INFO}
               for i in poses if i > 0]
    return {"variables": variables, "factors": factors}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--http", required=True)
    parser.add_argument("--zenoh", required=True)
    args = parser.parse_args()
    http = HttpClient(args.http, timeout=60)
    zenoh = ZenohClient(args.zenoh, mode="peer", timeout=30)
    checks = Checks()
    session = "py-robots"
    a, b = walk(0, 40), walk(13, 30)

    def ids():
        expect(robot_id("a") == "a" and robot_id("7") == "7", "letters and digits as they are")
        expect(robot_id("*") == "x2a", robot_id("*"))

    def follow():
        http.create_session("pose_graph_2d", session=session, robots={"min_closures": 3})
        latest = {"json": {}, "binary": {}}
        frames = []
        lock = threading.Lock()

        def on_json(event):
            if event.get("type") != "estimate":
                return
            with lock:
                for v in event["variables"]:
                    expect(robot_of_key(v["key"]) == "b", f"key {v['key']} on b's stream")
                    latest["json"][v["key"]] = v["value"]

        def on_binary(event):
            if event.get("type") != "estimate":
                return
            with lock:
                for array in event["arrays"].values():
                    for key, value in zip(array.keys.tolist(), array.values.tolist()):
                        latest["binary"][key] = value

        def on_frame(report):
            with lock:
                frames.append(report)

        zenoh.subscribe_robot_poses(session, "b", on_json, frame="odom")
        zenoh.subscribe_robot_poses(session, "b", on_binary, frame="odom", binary=True)
        zenoh.subscribe_robot_frame(session, "b", on_frame)
        time.sleep(0.5)  # let the subscriptions reach factord
        http.apply_batch(session, robot_batch("a", a, range(30)))
        http.apply_batch(session, robot_batch("b", b, range(20)))
        closures = [{"type": "between_se2", "keys": [robot_key("a", i), robot_key("b", j)],
                     "measurement": between(a[i], b[j]), "information": INFO}
                    for i, j in ((18, 5), (22, 9), (26, 13))]
        http.apply_batch(session, {"factors": closures})
        http.apply_batch(session, robot_batch("b", b, range(20, 30)))
        http.optimize(session, wait=True)
        want = {v["key"]: v["value"] for v in
                http.estimate(session, robot="b", frame="odom")["variables"]}

        def same(got):
            return got.keys() == want.keys() and all(
                abs(x - y) <= 1e-9 for k in want for x, y in zip(got[k], want[k]))

        deadline = time.monotonic() + 20
        while True:
            with lock:
                done = same(latest["json"]) and same(latest["binary"])
            if done:
                break
            expect(time.monotonic() < deadline,
                   f"b's stream: {len(latest['json'])} JSON, {len(latest['binary'])} binary "
                   f"poses of {len(want)}")
            time.sleep(0.05)
        for i in range(30):
            got, sent = want[robot_key("b", i)], between(b[0], b[i])
            d = between(sent, got)  # angles compared wrapped: π and -π are one heading
            expect(all(abs(x) < 1e-6 for x in d), f"b{i}: {got} vs {sent}")
        report = next(r for r in http.robots(session)["robots"] if r["robot"] == "b")
        with lock:
            expect(frames and frames[-1]["map_from_odom"] == report["map_from_odom"],
                   f"{frames} vs {report}")
        queried = zenoh.robot_estimate(session, "b", frame="odom")
        expect({v["key"]: v["value"] for v in queried["variables"]} == want, "robot_estimate")
        expect(zenoh.robot_frame(session, "b")["in_map"] is True, "robot_frame")
        return f"{len(want)} poses of b in its own frame, JSON and binary; frame {report['map_from_odom']}"

    checks.run("robot ids", ids)
    checks.run("robot b follows its own keys", follow)
    zenoh.close()
    http.close()
    return checks.exit_code()


if __name__ == "__main__":
    sys.exit(main())
