#!/usr/bin/env python3
"""The numpy client against a factord with authentication on, which this script starts itself
(a tokens file with two labels): the ≤ 15-line intel example with a token and without, numpy
values anywhere a list goes, covariance in and the same covariance out of the marginals, graph,
trajectory exports with stamps over HTTP and zenoh, fusion, one exception family for every
failure, and a script that forgets close() exiting at once.

    python clients/python/tests/test_numpy_auth.py --factord target/release/factord \
        --data-dir ../shared/data

Prints one line per check; exits non-zero when any fails (under CI=true a missing dataset too).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np

from harness import CLIENT_ROOT, Checks, Skip, TokenServer, expect, expect_raises, free_port

from factord_client import (Batch, FactordConnectionError, FactordError, HttpClient, Noise, Pose2,
                            ZenohClient)
from factord_client.batch import estimate_to_array

INTEL = "2d/sesync/intel.g2o"  # 1728 poses, 2512 edges (MANIFEST.md)
EXAMPLE = CLIENT_ROOT / "examples" / "stream_intel.py"
PYTHON_PATH = os.pathsep.join([str(CLIENT_ROOT), os.environ.get("PYTHONPATH", "")])
FORGETFUL_SCRIPT = textwrap.dedent("""
    import sys, numpy as np
    from factord_client import Batch, HttpClient, Pose2, Noise, ZenohClient
    z = ZenohClient(sys.argv[1])
    z.create_session("pose_graph_2d", session=sys.argv[2])
    z.subscribe(sys.argv[2], "acks", lambda event: None)
    z.subscribe(sys.argv[2], "*", lambda event: None)
    producer = z.producer(sys.argv[2], "forgetful")
    producer.send(Batch().pose(0, Pose2()).pose(1, np.array([1.0, 0, 0]))
                  .between(0, 1, Pose2(1, 0, 0), Noise.sigmas([0.1, 0.1, 0.1])))
    producer.flush(timeout=30)
    events = HttpClient(sys.argv[3], token=sys.argv[4]).events(sys.argv[2])
    print("done, no close()", flush=True)
""")


def relative(a: float, b: float) -> float:
    return abs(a - b) / max(abs(b), 1e-300)


def parse_tum(text: str) -> np.ndarray:
    rows = [line.split() for line in text.splitlines() if line and not line.startswith("#")]
    return np.array(rows, dtype=float).reshape(len(rows), 8)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--factord", required=True, help="the factord binary to start")
    parser.add_argument("--data-dir", type=Path, default=None)
    args = parser.parse_args()
    data_dir = args.data_dir or Path(os.environ.get("FACTORD_DATA", "../shared/data"))
    checks = Checks()
    with TokenServer(args.factord) as server:
        run_checks(checks, server, data_dir)
        expect_no_panic = not server.panicked()
    if not expect_no_panic:
        print(f"FAIL  the server panicked: see {server.log}")
        checks.failed.append("server panicked")
    return checks.exit_code()


def run_checks(checks: Checks, server: TokenServer, data_dir: Path) -> None:
    http = HttpClient(server.http, token=server.token)
    anonymous = HttpClient(server.http, token="", retries=0)

    def need_data(name: str) -> Path:
        path = data_dir / name
        if path.exists():
            return path
        if os.environ.get("CI") == "true":
            raise AssertionError(f"{path} missing (CI=true)")
        raise Skip(f"{path} not found")

    def auth_required() -> str:
        expect(anonymous.health()["status"] == "ok", "health is open")
        error = expect_raises(FactordError, anonymous.list_sessions, "no token")
        expect(error.status == 401 and error.code == "unauthorized"
               and error.field == "authorization", f"401 unauthorized at authorization: {error}")
        wrong = HttpClient(server.http, token="not-a-token-of-this-server", retries=0)
        expect(expect_raises(FactordError, wrong.list_sessions, "wrong token").status == 401,
               "a wrong token is 401")
        mine = http.create_session("pose_graph_2d")["session"]
        bob = HttpClient(server.http, token=server.other_token)
        error = expect_raises(FactordError, lambda: bob.stats(mine), "another label's session")
        expect(error.status == 404, f"another label's session is 404: {error}")
        http.delete_session(mine)
        return "401 without or with a wrong token (status, code, field); 404 across labels"

    def example_with_auth() -> str:
        lines = EXAMPLE.read_text().splitlines()
        expect(len(lines) <= 15, f"{EXAMPLE.name} has {len(lines)} lines (at most 15)")
        intel = need_data(INTEL)
        env = {**os.environ, "FACTORD_TOKEN": server.token, "PYTHONPATH": PYTHON_PATH}
        run = subprocess.run([sys.executable, str(EXAMPLE), str(intel), server.http], env=env,
                             capture_output=True, text=True, timeout=300)
        expect(run.returncode == 0, f"the example failed:\n{run.stdout}\n{run.stderr}")
        words = run.stdout.split()  # "session s1: poses (1728, 3), chi2 45.004696"
        session, chi2 = words[1].rstrip(":"), float(words[-1])
        expect("(1728, 3)" in run.stdout, f"an (N, 3) array of 1728 poses: {run.stdout}")
        job = http.run_job(intel.read_text())
        expect(relative(chi2, job["summary"]["final_chi2"]) < 1e-6,
               f"streamed chi2 {chi2} vs batch job {job['summary']['final_chi2']}")
        keys, poses = http.estimate_array(session)
        optimum = estimate_to_array(job["estimate"])
        expect(np.array_equal(keys, optimum.keys), "the same keys as the job")
        worst = float(np.abs(poses[:, :2] - optimum.values[:, :2]).max())
        expect(worst < 1e-4, f"poses differ from the job's by up to {worst} m")
        without = subprocess.run([sys.executable, str(EXAMPLE), str(intel), server.http],
                                 env={**env, "FACTORD_TOKEN": ""}, capture_output=True,
                                 text=True, timeout=60)
        expect(without.returncode != 0 and "401 unauthorized" in without.stderr,
               f"without a token: FactordError 401 expected:\n{without.stderr[-500:]}")
        http.delete_session(session)
        return (f"{len(lines)} lines; chi2 {chi2} == batch job; poses within {worst:.1e} m of "
                f"the job's; without a token: 401")

    def numpy_everywhere() -> str:
        s = http.create_session("pose_graph_2d")["session"]
        keys = np.arange(3, dtype=np.int64)
        ack = http.apply_batch(s, {
            "variables": [{"key": keys[0], "kind": "se2", "value": np.zeros(3), "fixed": True},
                          {"key": keys[1], "kind": "se2", "value": np.array([0.9, 0.1, 0.0]),
                           "stamp": np.float64(1.0)},
                          {"key": keys[2], "kind": "se2", "value": Pose2(2.1, 0, 0)}],
            "factors": [{"type": "between_se2", "keys": keys[[i, i + 1]],
                         "measurement": np.array([1.0, 0.0, 0.0]),
                         "information": np.eye(3).reshape(-1) * 100} for i in range(2)],
        }, wait=True)
        expect(ack["factor_ids"] == [0, 1], f"ack: {ack}")
        http.apply_batch(s, Batch().guess(2, Pose2(2.0, 0.0, 0.0)), wait=True)
        http.optimize(s, wait=True)
        estimate = http.estimate_array(s, since=np.int64(0), from_key=np.int64(0))
        expect(estimate.values.shape == (3, 3) and np.allclose(estimate.values[:, 0], [0, 1, 2]),
               f"the chain at 0, 1, 2: {estimate.values}")
        expect(np.isnan(estimate.stamps[0]) and estimate.stamps[1] == 1.0, "stamps back")
        poses = http.estimate_poses(s)
        expect(isinstance(poses[2], Pose2) and abs(poses[2].x - 2.0) < 1e-9, f"poses: {poses}")
        http.delete_session(s)
        return "np.int64 keys, ndarray values and information, Pose2 values and guesses, filters"

    def covariance_round_trip() -> str:
        s = http.create_session("pose_graph_2d")["session"]
        covariance = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
        http.apply_batch(s, Batch().pose(0, Pose2(), fixed=True).pose(1, None, kind="se2")
                         .between(0, 1, Pose2(1.0, 0.0, 0.0), Noise.covariance(covariance)),
                         wait=True)
        covariances, joint = http.covariances(s, np.array([0, 1]), joint=True)
        # From a fixed origin along a heading of 0 the residual is x1 minus the measurement, so
        # the marginal of pose 1 is exactly the measurement's covariance.
        expect(np.allclose(covariances[1], covariance, rtol=1e-9, atol=1e-12),
               f"covariance out {covariances[1]} != in {covariance}")
        expect(not covariances[0].any() and joint is not None and joint.shape == (6, 6),
               "the fixed pose has zero covariance; joint is 6x6")
        graph = http.graph(s)
        expect(graph["edges"] == [[0, 1]] and graph["dimension"] == 2, f"graph: {graph}")
        http.delete_session(s)
        return "Noise.covariance(C) in, marginal C out (correlated, to 1e-9); graph edges"

    def export_with_stamps() -> str:
        s = http.create_session("pose_graph_2d")["session"]
        stamps = np.array([10.0, 10.5, 11.25])
        values = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [1.5, 0.9, 1.0]])
        http.apply_batch(s, Batch().poses([0, 1, 2], values, stamps=stamps).fix(0), wait=True)
        tum = parse_tum(http.export(s, "tum"))
        expect(np.array_equal(tum[:, 0], stamps), f"TUM stamps {tum[:, 0]}")
        expect(np.allclose(tum[:, 1:3], values[:, :2]) and not tum[:, 3].any(), "positions")
        half = values[:, 2] / 2
        expect(np.allclose(tum[:, 6], np.sin(half)) and np.allclose(tum[:, 7], np.cos(half)),
               f"quaternions of the headings: {tum[:, 4:]}")
        kitti = [line.split() for line in http.export(s, "kitti").splitlines() if line]
        expect(len(kitti) == 3 and all(len(row) == 12 for row in kitti), f"kitti: {kitti}")
        g2o_lines = [line for line in http.export(s, "g2o").splitlines()
                     if line.startswith("VERTEX_SE2")]
        expect(len(g2o_lines) == 3, f"g2o: {g2o_lines}")
        expect_raises(ValueError, lambda: http.export(s, "csv"), "an unknown format")
        http.delete_session(s)
        return "TUM stamps, positions and quaternions; KITTI 3x12; g2o vertices"

    def over_zenoh() -> str:
        # zenoh peers are anonymous with tokens on: they reach sessions nobody owns (created
        # over zenoh), which any valid HTTP token reaches too.
        session = "numpy-zenoh"
        acks: list = []
        with ZenohClient(server.zenoh) as z:
            z.create_session("pose_graph_2d", session=session)
            z.subscribe(session, "acks", acks.append)
            values = np.cumsum(np.tile([[1.0, 0.0, 0.1]], (20, 1)), axis=0) - [1.0, 0.0, 0.1]
            with z.producer(session, "numpy-robot") as producer:
                producer.send(Batch().pose(0, values[0], stamp=0.0, fixed=True))
                for k in range(1, 20):
                    producer.send(Batch().pose(k, None, kind="se2", stamp=0.1 * k)
                                  .between(k - 1, k, Pose2(1.0, 0.0, 0.1),
                                           Noise.sigmas([0.1, 0.1, 0.02])))
                producer.flush(timeout=60)
                producer.optimize(wait=True)
            keys, poses = z.estimate_array(session)
            expect(poses.shape == (20, 3), f"zenoh estimate_array: {poses.shape}")
            over_http = http.estimate_array(session)
            expect(np.array_equal(poses, over_http.values), "zenoh and HTTP estimates agree")
            expect(z.export(session, "tum") == http.export(session, "tum"), "the same TUM")
            cov_z, _ = z.covariances(session, keys[-2:])
            cov_h, _ = http.covariances(session, keys[-2:])
            expect(all(np.allclose(cov_z[k], cov_h[k]) for k in cov_h), "the same covariances")
            expect(len(z.graph(session)["edges"]) == 19, "19 edges")
            deadline = time.monotonic() + 5
            while len(acks) < 20 and time.monotonic() < deadline:
                time.sleep(0.02)
            expect(len(acks) >= 20, f"{len(acks)} ack events of 20 batches")
            z.delete_session(session)
        return "producer sends Batch objects; estimate_array, export, covariances, graph agree"

    def slow_subscriber() -> str:
        # A callback stuck on the first ack: 3 more fit the queue, the other 17 are dropped;
        # the next ack after the gap comes with a client-side lagged marker before it.
        session = "slow-subscriber"
        events: list = []
        release = threading.Event()

        def stuck_on_first(event: dict) -> None:
            events.append(event)
            release.wait(timeout=60)

        with ZenohClient(server.zenoh) as z:
            z.create_session("pose_graph_2d", session=session)
            expect_raises(ValueError, lambda: z.subscribe(session, "acks", print, max_pending=0),
                          "max_pending 0")
            slow = z.subscribe(session, "acks", stuck_on_first, max_pending=3)
            with z.producer(session, "fast-robot") as producer:
                producer.send(Batch().pose(0, Pose2(), fixed=True))
                # The callback holds the first ack (out of the queue) before the rest come.
                deadline = time.monotonic() + 10
                while not events and time.monotonic() < deadline:
                    time.sleep(0.01)
                for k in range(1, 21):
                    producer.send(Batch().pose(k, None, kind="se2")
                                  .between(k - 1, k, Pose2(1.0, 0.0, 0.0),
                                           Noise.sigmas([0.1, 0.1, 0.1])))
                producer.flush(timeout=60)
                deadline = time.monotonic() + 10
                while slow.dropped < 17 and time.monotonic() < deadline:
                    time.sleep(0.02)
                expect(slow.dropped == 17, f"{slow.dropped} acks dropped of 21, 1 + 3 kept")
                release.set()
                # The next ack must find room: wait until the three queued acks are handed out
                # (the fourth event taken leaves the queue empty), or on a loaded host it is
                # dropped as the 18th and no marker ever comes.
                deadline = time.monotonic() + 10
                while len(events) < 4 and time.monotonic() < deadline:
                    time.sleep(0.01)
                expect(len(events) == 4, f"{len(events)} events after the release, 4 expected")
                producer.send(Batch().pose(21, None, kind="se2")
                              .between(20, 21, Pose2(1.0, 0.0, 0.0),
                                       Noise.sigmas([0.1, 0.1, 0.1])))
                producer.flush(timeout=60)
            deadline = time.monotonic() + 10
            while len(events) < 6 and time.monotonic() < deadline:
                time.sleep(0.02)
            seen = [e.get("producer_seq") if e.get("type") == "ack" else e for e in events]
            expect(seen == [1, 2, 3, 4, {"type": "lagged", "skipped": 17, "source": "client"}, 22],
                   f"events: {seen}")
            z.delete_session(session)
        return "max_pending 3: 4 acks, a lagged marker for the 17 dropped, then the next ack"

    def fusion() -> str:
        s = http.create_session("sliding_window")["session"]
        sigmas = {"position": 0.01, "rotation": 0.01, "velocity": 0.1, "accel_bias": 0.1,
                  "gyro_bias": 0.01}
        messages = [{"type": "start", "t": 0.0, "position": np.zeros(3),
                     "rotation_xyzw": np.array([0.0, 0.0, 0.0, 1.0]), "sigmas": sigmas,
                     "window": 5}]
        messages += [{"type": "imu", "t": 0.01 * i, "accel": np.array([0.0, 0.0, 9.81]),
                      "gyro": np.zeros(3)} for i in range(1, 11)]
        messages.append({"type": "keyframe", "t": np.float64(0.1)})
        answer = http.fusion(s, messages)
        expect(answer["applied"] == 12 and answer["keyframes"] == [0, 1], f"fusion: {answer}")
        error = expect_raises(FactordError, lambda: http.fusion(s, [{"type": "imu", "t": 0.0,
                                                                     "accel": np.zeros(3),
                                                                     "gyro": np.zeros(3)}]),
                              "an IMU sample before the last keyframe")
        expect(error.field == "messages[0]", f"the refused message is named: {error}")
        http.delete_session(s)
        return f"12 messages with ndarray fields applied; a late IMU sample refused at {error.field}"

    def one_error_family() -> str:
        s = http.create_session("pose_graph_2d")["session"]
        error = expect_raises(FactordError, lambda: http.apply_batch(
            s, Batch().between(0, 1, Pose2(1, 0, 0), Noise.sigmas([1, 1, 1]))), "unknown keys")
        expect(error.status == 422 and error.code == "unknown_variable"
               and (error.field or "").startswith("factors[0]"), f"422 at factors[0]: {error}")
        http.delete_session(s)
        refused = HttpClient(f"http://127.0.0.1:{free_port()}", retries=0)
        error = expect_raises(FactordConnectionError, refused.health, "nobody listening")
        expect(isinstance(error, FactordError) and isinstance(error, ConnectionError)
               and error.code == "connection_failed", f"connection_failed: {error!r}")
        error = expect_raises(FactordConnectionError,
                              lambda: ZenohClient(f"tcp/127.0.0.1:{free_port()}"),
                              "a zenoh endpoint nobody listens on")
        expect("zenoh" in error.message, f"zenoh's error wrapped: {error}")
        z = ZenohClient(server.zenoh, reconnect_wait=0.0)
        error = expect_raises(FactordError, lambda: z.stats("no-such-session"), "rpc error")
        expect(error.status == 404, f"rpc error reply as FactordError 404: {error}")
        error = expect_raises(FactordConnectionError,
                              lambda: z._query("nobody/answers/here", None, 2.0, safe=False),
                              "no queryable")
        expect(error.code == "no_reply", f"no_reply: {error}")
        z.close()
        error = expect_raises(FactordError, z.health, "a closed client")
        expect(error.code == "closed", f"closed: {error}")
        expect_raises(FactordError, lambda: z.producer("x", "p", resume=False),
                      "a producer on a closed client")
        return "422 with field; refused HTTP; zenoh open, rpc error, no reply, closed client"

    def forgotten_close_exits() -> str:
        started = time.monotonic()
        run = subprocess.run(
            [sys.executable, "-c", FORGETFUL_SCRIPT, server.zenoh, "forgetful", server.http,
             server.token],
            env={**os.environ, "PYTHONPATH": PYTHON_PATH}, capture_output=True, text=True,
            timeout=30)  # raises TimeoutExpired (the check fails) when the process hangs
        took = time.monotonic() - started
        expect(run.returncode == 0 and "done, no close()" in run.stdout,
               f"the script failed:\n{run.stdout}\n{run.stderr}")
        expect(took < 5.0, f"the process took {took:.1f} s to exit after its last line")
        http.delete_session("forgetful")
        return f"subscriptions, a producer and an SSE stream left open: exited in {took:.2f} s"

    checks.run("auth: 401 without a token, sessions private to their label", auth_required)
    checks.run("the 15-line intel example with auth on: (N, 3) estimate == batch job",
               example_with_auth)
    checks.run("numpy values accepted anywhere a list goes", numpy_everywhere)
    checks.run("covariance in, the same marginal covariance out; graph", covariance_round_trip)
    checks.run("export: TUM with stamps, KITTI, g2o", export_with_stamps)
    checks.run("zenoh: producer of Batch objects, arrays and exports agree with HTTP",
               over_zenoh)
    checks.run("a slow zenoh subscriber: bounded queue, told what it missed", slow_subscriber)
    checks.run("fusion messages with numpy fields", fusion)
    checks.run("one exception family: service, HTTP and zenoh failures", one_error_family)
    checks.run("a script that forgets close() exits at once", forgotten_close_exits)


if __name__ == "__main__":
    sys.exit(main())
