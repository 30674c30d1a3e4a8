"""IncrementalSession: a server session run in process through the service's command API (no
server, no socket). The same batches as a server takes, the same answers and refusals. Run by
tests/tools/python_native.rs."""

import math
import os
import threading

import numpy as np
import pytest

import factord
from factord import expressions as fx

DATA = os.environ.get("FACTORD_DATA", os.path.join(os.path.dirname(__file__), "../../../../../shared/data"))
M3500 = os.path.join(DATA, "2d/carlone/input_M3500_g2o.g2o")


def read_g2o_2d(path):
    """Vertices {id: [x, y, θ]} and edges [(i, j, [dx, dy, dθ], information 3×3 upper triangle)]."""
    vertices, edges = {}, []
    with open(path) as f:
        for line in f:
            t = line.split()
            if not t:
                continue
            if t[0] == "VERTEX_SE2":
                vertices[int(t[1])] = [float(v) for v in t[2:5]]
            elif t[0] == "EDGE_SE2":
                i, j = int(t[1]), int(t[2])
                m = [float(v) for v in t[3:6]]
                a, b, c, d, e, g = (float(v) for v in t[6:12])
                edges.append((i, j, m, [[a, b, c], [b, d, e], [c, e, g]]))
    return vertices, edges


@pytest.fixture(scope="module")
def m3500():
    if not os.path.exists(M3500):
        pytest.skip(f"{M3500} missing")
    return read_g2o_2d(M3500)


def test_a_streamed_file_ends_at_the_batch_optimum(m3500):
    vertices, edges = m3500
    by_later = {}
    for e in edges:
        by_later.setdefault(max(e[0], e[1]), []).append(e)
    with factord.IncrementalSession("pose_graph_2d") as s:
        for k in sorted(vertices):
            factors = [
                {"type": "between_se2", "keys": [i, j], "measurement": m, "information": sum(info, [])}
                for (i, j, m, info) in by_later.get(k, [])
            ]
            batch = {"variables": [{"key": k, "kind": "se2", "value": vertices[k]}], "factors": factors}
            ack = s.apply_batch(batch)
            assert ack["sequence"] == k + 1
        s.optimize(wait=True)
        streamed = s.stats()["chi2"]
        keys, poses = s.estimate_array()
        assert len(keys) == len(vertices)
    graph, initial = factord.readG2o(M3500, False)
    _, summary = factord.solve(graph, initial, method="gn", initialization="auto")
    # The batch optimum within 1e-5, as the service's benchmarks hold an idle estimate to. An
    # optimize stops when a step gains less than 1e-6 of chi2, so where the stream's solves left
    # it decides the last digits: 1.5e-6 above once in a loaded full run.
    assert streamed == pytest.approx(summary["final_chi2"], rel=1e-5)


def test_refusals_carry_the_servers_error_body():
    with factord.IncrementalSession("pose_graph_2d") as s:
        two = [{"key": 0, "kind": "se2", "value": [0, 0, 0]}, {"key": 1, "kind": "se2", "value": [1, 0, 0]}]
        bad = {"variables": two, "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0], "sigmas": [1, 1, 1]}]}
        with pytest.raises(factord.ServiceError) as raised:
            s.apply_batch(bad)
        e = raised.value
        assert e.status == 400 and e.field == "factors[0].measurement", (e.status, e.code, e.field)
        assert isinstance(e, factord.FactordError)
        with pytest.raises(factord.ServiceError) as raised:
            s.apply_batch({"variables": [{"key": 0, "kind": "se3", "value": [0, 0, 0]}]})
        assert raised.value.field is not None and raised.value.field.startswith("variables[0]")
        # Nothing was applied.
        assert s.stats()["sequence"] == 0
    with pytest.raises(factord.ServiceError) as raised:
        factord.IncrementalSession("pose_graph_9d")
    assert raised.value.status == 400 and raised.value.field == "kind"


def test_a_python_factor_type_runs_in_a_session():
    Beacon = fx.FactorType(
        "beacon_range", variables=[("x", "se2")], parameters=[("beacon", "point2"), ("range", "scalar")],
        residual=lambda x, beacon, range: fx.norm(beacon - x.translation()) - range,
    )
    with factord.IncrementalSession("pose_graph_2d", factor_types=[Beacon.definition]) as s:
        s.apply_batch({
            "variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}, {"key": 1, "kind": "se2", "value": [0.9, 0.2, 0.1]}],
            "factors": [
                {"type": "prior_se2", "keys": [0], "measurement": [0, 0, 0], "sigmas": [0.01, 0.01, 0.01]},
                {"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.05]},
                {"type": "beacon_range", "keys": [1], "measurement": [1, 5, 5], "sigmas": [0.01]},
                {"type": "beacon_range", "keys": [1], "measurement": [4, 0, 3], "sigmas": [0.01]},
            ],
        }, wait=True)
        s.optimize()
        pose = {v["key"]: v["value"] for v in s.estimate()["variables"]}[1]
        np.testing.assert_allclose(pose[:2], [1.0, 0.0], atol=1e-6)


def test_sessions_in_two_threads_run_side_by_side():
    # Each wait releases the GIL: two Python threads stream into two sessions at once.
    results = {}

    def stream(name):
        with factord.IncrementalSession("pose_graph_2d") as s:
            for k in range(200):
                a = 0.05 * k
                variables = [{"key": k, "kind": "se2", "value": [math.cos(a) * 5, math.sin(a) * 5, a + math.pi / 2]}]
                factors = []
                if k == 0:
                    factors.append({"type": "prior_se2", "keys": [0], "measurement": variables[0]["value"], "sigmas": [0.01] * 3})
                else:
                    factors.append({"type": "between_se2", "keys": [k - 1, k], "measurement": [0.25, 0.0, 0.05], "sigmas": [0.05, 0.05, 0.01]})
                s.apply_batch({"variables": variables, "factors": factors}, wait=True)
            results[name] = s.stats()["chi2"]

    threads = [threading.Thread(target=stream, args=(n,)) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert set(results) == {"a", "b"} and results["a"] == pytest.approx(results["b"], rel=1e-9)


def test_a_dropped_session_is_deleted_from_the_shared_service():
    import gc
    import json

    s = factord.IncrementalSession("pose_graph_2d")
    name = s.name
    service = factord.session.shared_service()
    listed = lambda: [x["session"] for x in json.loads(service.execute('{"op": "list_sessions"}'))["sessions"]]
    assert name in listed()
    del s
    gc.collect()
    assert name not in listed()


def test_the_service_answers_raw_commands():
    service = factord.Service(workers=1)
    import json

    health = json.loads(service.execute(json.dumps({"op": "health"})))
    assert health["status"] == "ok"
    with pytest.raises(factord.ServiceError) as raised:
        service.execute('{"op": "frobnicate"}')
    assert raised.value.status == 400
