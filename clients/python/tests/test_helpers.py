#!/usr/bin/env python3
"""Checks of the client's numpy side that need no server: poses, noise models, batches built
from arrays, the JSON encoder, estimates as arrays, the typing files, and that every HTTP route
of proto/v1/openapi.json has a client method.

    python clients/python/tests/test_helpers.py

Prints one line per check; exits non-zero when any fails.
"""

from __future__ import annotations

import importlib.resources
import json
import math
import struct
import sys
import typing

import numpy as np

from harness import REPO_ROOT, Checks, expect, expect_raises

from factord_client import (Batch, HttpClient, Noise, Pose2, Pose3, ZenohClient, dumps, robot_key,
                            robot_of_key, wire)
from factord_client.batch import estimate_to_array, marginals_to_arrays
from factord_client.poses_binary import PosesBinaryError, decode_event, decode_poses

# openapi operations that are not API calls a client makes: the web view's pages and assets,
# and the WebSocket (the same events as `events()`, which needs no extra dependency).
# Pages, their assets, the WebSocket, and the browser's login (clients send the bearer token).
NOT_CLIENT_CALLS = {"index_page", "session_page", "script", "style", "docs_page", "docs_script",
                    "websocket", "plots_script", "operator_script", "login", "logout"}
# operationId -> method name where they differ.
METHOD_OF = {"job": "run_job", "openapi_json": "openapi", "list_robots": "robots",
             "list_outliers": "outliers"}


def close(a, b, tol=1e-12) -> bool:
    return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), atol=tol, rtol=0))


def pose2_group() -> str:
    a, b = Pose2(1.0, 2.0, 0.5), Pose2(-0.3, 0.7, 3.0)
    expect(close((a * b).matrix(), a.matrix() @ b.matrix()), "compose is the matrix product")
    expect(close(a.between(b).matrix(), np.linalg.inv(a.matrix()) @ b.matrix()),
           "between is a⁻¹ b")
    expect((a * a.inverse()).almost_equal(Pose2()), "a a⁻¹ is the identity")
    expect(abs((a * b).theta) <= math.pi, f"heading wrapped: {(a * b).theta}")
    expect(Pose2.from_matrix(a.matrix()).almost_equal(a), "matrix round trip")
    expect(Pose2.from_array(np.array([1, 2, 0.5])) == a, "from_array of an ndarray")
    expect(close(np.asarray(a), [1, 2, 0.5]), "np.asarray(pose)")
    expect(a.variable(7, stamp=1.25) == {"key": 7, "kind": "se2", "value": [1.0, 2.0, 0.5],
                                         "stamp": 1.25}, f"variable: {a.variable(7, 1.25)}")
    expect(close(a.transform_from([1, 0]), (a * Pose2(1, 0, 0)).translation()), "transform_from")
    expect_raises(ValueError, lambda: Pose2.from_array([1, 2]), "two numbers")
    return "compose, between, inverse, wrap, matrix, wire"


def pose3_group() -> str:
    rng = np.random.default_rng(3)
    poses = [Pose3.from_rotation_vector(rng.normal(size=3), rng.normal(size=3)) for _ in range(5)]
    for a, b in zip(poses, poses[1:]):
        expect(close((a * b).matrix(), a.matrix() @ b.matrix(), 1e-12), "compose = product")
        expect(close(a.between(b).matrix(), np.linalg.inv(a.matrix()) @ b.matrix(), 1e-12),
               "between is a⁻¹ b")
        expect(Pose3.from_matrix(a.matrix()).almost_equal(a, 1e-12), "matrix round trip")
        expect(Pose3.from_matrix(a.matrix()[:3].reshape(-1)).almost_equal(a, 1e-12),
               "a KITTI row (3x4 flattened)")
        r = a.rotation_matrix()
        expect(close(r @ r.T, np.eye(3), 1e-12) and abs(np.linalg.det(r) - 1) < 1e-12,
               "rotation matrix orthonormal")
    # A quaternion and its negative are the same rotation: one canonical spelling (w >= 0).
    q = np.array([0.1, -0.2, 0.3, -0.9])
    expect(Pose3([0, 0, 0], q) == Pose3([0, 0, 0], -q), "q and -q compare equal")
    half_turn = Pose3.from_rotation_vector([0, 0, math.pi])
    expect(close(half_turn.transform_from([1, 0, 0]), [-1, 0, 0], 1e-12), "half turn about z")
    wire_value = poses[0].to_wire()
    expect(len(wire_value) == 7 and all(type(v) is float for v in wire_value), "7 floats")
    expect(Pose3.from_array(wire_value).almost_equal(poses[0], 1e-15), "wire round trip")
    expect_raises(ValueError, lambda: Pose3([0, 0, 0], [0, 0, 0, 0]), "zero quaternion")
    return "compose, between, inverse, quaternion <-> matrix, canonical sign"


def noise_models() -> str:
    s = Noise.sigmas([0.1, 0.2, 0.05])
    expect(s.to_wire() == {"sigmas": [0.1, 0.2, 0.05]}, f"sigmas sent as sigmas: {s.to_wire()}")
    expect(close(s.information_matrix, np.diag([100, 25, 400]), 1e-9), "information of sigmas")
    # A correlated covariance: the information sent is its inverse (upper triangle, g2o order).
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    n = Noise.covariance(cov)
    expect(close(n.information_matrix, np.linalg.inv(cov), 1e-9), "inverse of the covariance")
    info = np.linalg.inv(cov)
    triangle = [info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2]]
    expect(close(n.to_wire()["information"], triangle, 1e-9), "upper triangle row by row")
    expect(close(n.covariance_matrix, cov, 1e-12), "covariance back")
    expect(close(Noise.information(triangle).information_matrix, info, 1e-12),
           "information from an upper triangle")
    expect(Noise.isotropic(6, 0.1).dim == 6, "isotropic")
    expect_raises(ValueError, lambda: Noise.covariance(np.diag([1.0, -1.0, 1.0])),
                  "a covariance that is not positive definite")
    expect_raises(ValueError, lambda: Noise.covariance([[1.0, 0.5], [0.0, 1.0]]),
                  "an asymmetric covariance")
    expect_raises(ValueError, lambda: Noise.sigmas([0.1, 0.0]), "a zero sigma")
    expect_raises(ValueError, lambda: Noise.information([1.0, 2.0]), "2 numbers: no triangle")
    return "sigmas, covariance -> information (correlated), information, refusals"


def encoder() -> str:
    value = {"a": np.arange(3), "b": np.float32(0.5), "c": np.int64(7), "d": np.bool_(True),
             "e": Pose2(1, 2, 0), "f": [np.zeros((2, 2))], "g": Noise.sigmas([1.0])}
    decoded = json.loads(dumps(value))
    expect(decoded == {"a": [0, 1, 2], "b": 0.5, "c": 7, "d": True, "e": [1.0, 2.0, 0.0],
                       "f": [[[0.0, 0.0], [0.0, 0.0]]], "g": {"sigmas": [1.0]}},
           f"decoded: {decoded}")
    error = expect_raises(TypeError, lambda: dumps({"x": object()}), "an unknown object")
    expect("numpy" in str(error), f"the message says what is encoded: {error}")
    return "ndarray, numpy scalars, poses, Noise"


def batch_builder() -> str:
    keys = np.array([0, 1, 2], dtype=np.int64)
    values = np.array([[0, 0, 0], [1, 0, 0.1], [2, 0.1, 0.2]])
    pairs = np.array([[0, 1], [1, 2]])
    measurements = np.array([[1, 0, 0.1], [1, 0.1, 0.1]])
    g2o_information = np.array([[100, 0, 0, 100, 0, 400]] * 2)
    batch = (Batch().poses(keys, values, stamps=[0.0, 0.5, 1.0])
             .between_many(pairs, measurements, g2o_information)
             .prior(0, Pose2(), Noise.sigmas([0.01, 0.01, 0.01])).fix(0).to_wire())
    expect(batch["variables"][1] == {"key": 1, "kind": "se2", "value": [1.0, 0.0, 0.1],
                                     "stamp": 0.5}, f"variable: {batch['variables'][1]}")
    expect(batch["factors"][1] == {"type": "between_se2", "keys": [1, 2],
                                   "measurement": [1.0, 0.1, 0.1],
                                   "information": [100.0, 0.0, 0.0, 100.0, 0.0, 400.0]},
           f"factor: {batch['factors'][1]}")
    expect(batch["factors"][2]["type"] == "prior_se2" and batch["fix"] == [0], "prior, fix")
    expect(json.loads(dumps(batch)) == batch, "plain JSON values only")
    # 3D: measurements as poses, one Noise shared by every factor, (M, d, d) information.
    b3 = (Batch().pose(0, Pose3()).pose(1, None, kind="se3")
          .between(0, 1, Pose3([1, 0, 0]), Noise.covariance(np.eye(6) * 0.01))
          .between_many([[0, 1]], [Pose3([1, 0, 0]).to_wire()], np.eye(6)[None] * 2)
          .to_wire())
    expect(b3["factors"][0]["type"] == "between_se3"
           and close(b3["factors"][0]["information"][:6], [100, 0, 0, 0, 0, 0], 1e-9),
           f"between_se3 information: {b3['factors'][0]}")
    expect(len(b3["factors"][1]["information"]) == 21, "6x6 upper triangle: 21 numbers")
    expect("value" not in b3["variables"][1], "a predicted variable has no value")
    expect_raises(ValueError, lambda: Batch().between(0, 1, Pose2(), Noise.sigmas([1, 1])),
                  "noise of the wrong dimension")
    expect_raises(ValueError, lambda: Batch().poses([0, 1], np.zeros((3, 3))),
                  "2 keys, 3 values")
    expect_raises(ValueError, lambda: Batch().between_many([[0, 1]], [[1, 0, 0]],
                                                           np.zeros((2, 6))),
                  "information rows for 2 factors, 1 pair")
    return "poses(N,3) + between_many(M,6) == the hand-written wire batch; 3D; refusals"


def estimates_as_arrays() -> str:
    estimate = {"session": "s", "sequence": 4, "variables": [
        {"key": 2, "kind": "se2", "value": [2, 0, 0], "changed": 4, "stamp": 0.2},
        {"key": 0, "kind": "se2", "value": [0, 0, 0], "changed": 1, "stamp": 0.0},
        {"key": 9, "kind": "point2", "value": [5, 5], "changed": 4},
        {"key": 1, "kind": "se2", "value": [1, 0, 0.5], "changed": 2}]}
    array = estimate_to_array(estimate)
    keys, values = array
    expect(array.kind == "se2" and keys.tolist() == [0, 1, 2], f"pose keys sorted: {keys}")
    expect(values.shape == (3, 3) and close(values[1], [1, 0, 0.5]), f"values: {values}")
    expect(np.isnan(array.stamps[1]) and array.stamps[2] == 0.2, f"stamps: {array.stamps}")
    expect(array.extra_kinds == ["point2"], "the landmarks are named")
    landmarks = estimate_to_array(estimate, kind="point2")
    expect(landmarks.values.shape == (1, 2), "landmarks on request")
    expect(array.poses()[1] == Pose2(1, 0, 0.5) and close(array.value(2), [2, 0, 0]), "poses")
    empty = estimate_to_array({"session": "s", "sequence": 0, "variables": []})
    expect(empty.values.shape == (0, 3), f"empty: {empty.values.shape}")
    covariances, joint = marginals_to_arrays({
        "session": "s", "sequence": 1, "solves": 1, "gauge_fixed": [], "seconds": 0.0,
        "reused_factorization": False, "factorize_seconds": 0.0,
        "variables": [{"key": 3, "kind": "se2", "fixed": False, "covariance": np.eye(3).tolist()}]})
    expect(covariances[3].shape == (3, 3) and joint is None, "covariances as arrays")
    return "(N, 3) sorted by key, stamps NaN where absent, landmarks apart"


def binary_group(kind: str, records) -> bytes:
    """A group of proto/v1/poses-binary.md, packed by hand (not by the code under test)."""
    dimension = len(records[0][2])
    out = struct.pack("<B", len(kind)) + kind.encode() + struct.pack("<BI", dimension, len(records))
    for key, changed, value in records:
        out += struct.pack(f"<QQ{dimension}d", key, changed, *value)
    return out


def binary_estimates() -> str:
    groups = [binary_group("se2", [(4, 7, (1.0, 2.0, 0.5)), (5, 9, (3.0, -1e-300, -0.0))]),
              binary_group("point2", [(100, 8, (7.0, 8.0))]),
              binary_group("se2", [(2, 3, (0.0, 0.0, math.pi))])]
    payload = struct.pack("<4sIQI", b"FDPB", 1, 9, len(groups)) + b"".join(groups)
    event = decode_poses(payload, "s")
    expect(event["type"] == "estimate" and event["sequence"] == 9, str(event))
    poses = event["arrays"]["se2"]
    expect(poses.keys.tolist() == [2, 4, 5], f"sorted by key across groups: {poses.keys}")
    expect(poses.values.shape == (3, 3) and poses.values[0, 2] == math.pi, f"{poses.values}")
    expect(poses.values[2, 1] == -1e-300 and math.copysign(1, poses.values[2, 2]) < 0,
           "values bit for bit")
    expect(poses.changed.tolist() == [3, 7, 9] and np.isnan(poses.stamps).all(), "changed")
    expect(poses.extra_kinds == ["point2"], "the other kinds are named")
    landmarks = event["arrays"]["point2"]
    expect(landmarks.values.tolist() == [[7.0, 8.0]] and landmarks.keys.tolist() == [100], "landmarks")
    empty = decode_poses(struct.pack("<4sIQI", b"FDPB", 1, 3, 0))
    expect(empty["arrays"] == {} and empty["sequence"] == 3, f"empty: {empty}")
    marker = {"type": "lagged", "session": "s", "skipped": 4}
    expect(decode_event(json.dumps(marker).encode()) == marker, "a JSON marker passes through")
    newer = bytearray(payload)
    newer[4] = 2
    for bad, what in [(payload[:-1], "cut short"), (payload + b"\0", "after the last group"),
                      (bytes(newer), "version 2"), (b"XXXX" + payload[4:], "FDPB")]:
        error = expect_raises(PosesBinaryError, lambda b=bad: decode_poses(b), what)
        expect(what in str(error), f"{what}: {error}")
    return "two se2 runs and a point2 run, bit for bit; empty; marker; damaged bytes refused"


def typing_files() -> str:
    package = importlib.resources.files("factord_client")
    expect(package.joinpath("py.typed").is_file(), f"py.typed missing in {package}")
    hints = typing.get_type_hints(HttpClient.estimate)
    expect(hints["return"] is wire.Estimate, f"estimate returns wire.Estimate: {hints}")
    expect(typing.get_type_hints(HttpClient.apply_batch)["return"] is wire.BatchAck, "BatchAck")
    expect("stamp" in typing.get_type_hints(wire.VariableSpec), "VariableSpec has stamp")
    expect(wire.VariableSpec.__required_keys__ == frozenset({"key", "kind"}),
           f"required keys: {wire.VariableSpec.__required_keys__}")
    return f"py.typed in {package}; TypedDict answers"


def every_route_has_a_method() -> str:
    spec = json.loads((REPO_ROOT / "proto/v1/openapi.json").read_text())
    operations = [(method.upper(), path, op["operationId"])
                  for path, item in spec["paths"].items()
                  for method, op in item.items() if isinstance(op, dict) and "operationId" in op]
    missing = [f"{m} {p} ({op})" for m, p, op in operations
               if op not in NOT_CLIENT_CALLS and not hasattr(HttpClient, METHOD_OF.get(op, op))]
    expect(not missing, f"routes without an HttpClient method: {missing}")
    # The session routes that have an rpc command have a ZenohClient method of the same name.
    zenoh_missing = [op for op in ("health", "list_sessions", "create_session", "stats",
                                   "delete_session", "apply_batch", "fusion", "optimize",
                                   "set_auto_optimize", "define_factor_types", "estimate",
                                   "producer_status", "list_producers", "cancel", "graph",
                                   "marginals", "robots", "outliers")
                     if not hasattr(ZenohClient, op)]
    expect(not zenoh_missing, f"ZenohClient lacks {zenoh_missing}")
    for extra in ("estimate_array", "estimate_poses", "covariances", "export"):
        expect(hasattr(HttpClient, extra) and hasattr(ZenohClient, extra), f"both have {extra}")
    covered = len(operations) - len([o for o in operations if o[2] in NOT_CLIENT_CALLS])
    return f"{covered} operations covered (pages, assets and the WebSocket are not calls)"


def robot_keys() -> str:
    expect(robot_key("b", 42) == (ord("b") << 56) | 42, "GTSAM Symbol('b', 42)")
    expect(robot_of_key(robot_key("a", 7)) == "a" and robot_of_key(42) is None, "robot of a key")
    expect_raises(ValueError, lambda: robot_key("ab", 1), "two characters")
    expect_raises(ValueError, lambda: robot_key("a", 1 << 56), "index past 2^56")
    return "robot_key / robot_of_key are GTSAM's Symbol encoding"


def main() -> int:
    checks = Checks()
    checks.run("Pose2 group operations and encodings", pose2_group)
    checks.run("Pose3 group operations and encodings", pose3_group)
    checks.run("noise from sigmas, covariance or information", noise_models)
    checks.run("JSON encoder takes numpy values and helpers", encoder)
    checks.run("Batch from arrays equals the wire batch", batch_builder)
    checks.run("estimates and marginals as numpy arrays", estimates_as_arrays)
    checks.run("binary estimates (bin/poses) as numpy arrays", binary_estimates)
    checks.run("typed: py.typed and TypedDicts", typing_files)
    checks.run("a method for every HTTP route of openapi.json", every_route_has_a_method)
    checks.run("robot keys", robot_keys)
    return checks.exit_code()


if __name__ == "__main__":
    sys.exit(main())
