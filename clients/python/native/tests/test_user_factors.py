"""User-defined factors in process: GTSAM's CustomFactor (a Python error function with its own
Jacobians, in GTSAM's tangent conventions) and FactorType (a Python function recorded into the
expression language and differentiated by the library). Run by tests/tools/python_native.rs."""

import json
import math
import threading

import numpy as np
import pytest

import factord as gtsam
from factord import expressions as fx
from factord.symbol_shorthand import L, X

ODOMETRY = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2, 0.2, 0.1]))
GPS2 = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
GPS3 = gtsam.noiseModel.Isotropic.Sigma(3, 0.5)


def gps_pose2(measured):
    """A 2D position fix: error t - m; ∂t/∂ξ = [R | 0] in GTSAM's body-frame tangent."""

    def error(this, values, H):
        pose = values.atPose2(this.keys()[0])
        if H is not None:
            H[0] = np.hstack([pose.rotation().matrix(), np.zeros((2, 1))])
        return pose.translation() - measured

    return error


def gps_pose3(measured):
    """A 3D position fix: error t - m; ∂t/∂ξ = [0 | R] (GTSAM: rotation first)."""

    def error(this, values, H):
        pose = values.atPose3(this.keys()[0])
        if H is not None:
            H[0] = np.hstack([np.zeros((3, 3)), pose.rotation().matrix()])
        return pose.translation() - measured

    return error


def square_walk(n=12, seed=3):
    """Odometry around a square with noisy fixes at every pose, and a drifted start."""
    rng = np.random.default_rng(seed)
    truth = [gtsam.Pose2(0.0, 0.0, 0.0)]
    step = gtsam.Pose2(1.0, 0.0, math.pi / 2 / 3)
    for _ in range(n - 1):
        truth.append(truth[-1].compose(step))
    fixes = [p.translation() + rng.normal(0, 0.3, 2) for p in truth]
    initial = gtsam.Values()
    for i, p in enumerate(truth):
        initial.insert(X(i), gtsam.Pose2(p.x() + 0.4 * math.sin(i), p.y() - 0.3, p.theta() + 0.2))
    return truth, step, fixes, initial


def odometry_graph(n, step):
    graph = gtsam.NonlinearFactorGraph()
    for i in range(n - 1):
        graph.add(gtsam.BetweenFactorPose2(X(i), X(i + 1), step, ODOMETRY))
    return graph


def is_local_minimum(graph, values, keys, eps=1e-4):
    """No small step along any tangent direction of any variable lowers the error."""
    at = graph.error(values)
    for k in keys:
        pose = values.atPose2(k)
        for d in range(3):
            for sign in (-1.0, 1.0):
                xi = np.zeros(3)
                xi[d] = sign * eps
                moved = gtsam.Values(values)
                moved.update(k, pose.retract(xi))
                if graph.error(moved) < at - 1e-12:
                    return False
    return True


def test_custom_factor_reaches_the_expression_factors_optimum():
    n = 12
    _, step, fixes, initial = square_walk(n)
    custom = odometry_graph(n, step)
    recorded = odometry_graph(n, step)
    Gps = fx.FactorType(
        "gps2", variables=[("x", "se2")], parameters=[("m", "point2")],
        residual=lambda x, m: x.translation() - m,
    )
    for i, m in enumerate(fixes):
        custom.add(gtsam.CustomFactor(GPS2, [X(i)], gps_pose2(m)))
        recorded.add(Gps([X(i)], [m], GPS2))
    a = gtsam.GaussNewtonOptimizer(custom, initial).optimize()
    b = gtsam.GaussNewtonOptimizer(recorded, initial).optimize()
    for i in range(n):
        np.testing.assert_allclose(a.atPose2(X(i)).matrix(), b.atPose2(X(i)).matrix(), atol=1e-9)
    assert custom.error(a) == pytest.approx(recorded.error(b), rel=1e-9)
    # Jacobians taken in the wrong tangent would stop Gauss-Newton elsewhere: check the point.
    assert is_local_minimum(custom, a, [X(i) for i in range(n)])


def test_custom_factor_pose3_jacobian_is_converted_from_gtsams_order():
    rng = np.random.default_rng(7)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    step = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.1, -0.05), gtsam.Point3(1.0, 0.2, 0.1))
    pose = gtsam.Pose3()
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.05, 0.2, 0.2, 0.2]))
    Gps = fx.FactorType(
        "gps3", variables=[("x", "se3")], parameters=[("m", "point3")],
        residual=lambda x, m: x.translation() - m,
    )
    recorded = gtsam.NonlinearFactorGraph()
    for i in range(8):
        if i:
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, odo))
            recorded.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, odo))
            pose = pose.compose(step)
        m = pose.translation() + rng.normal(0, 0.3, 3)
        graph.add(gtsam.CustomFactor(GPS3, [X(i)], gps_pose3(m)))
        recorded.add(Gps([X(i)], [m], GPS3))
        initial.insert(X(i), pose.retract(rng.normal(0, 0.1, 6)))
    a = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    b = gtsam.LevenbergMarquardtOptimizer(recorded, initial).optimize()
    for i in range(8):
        np.testing.assert_allclose(a.atPose3(X(i)).matrix(), b.atPose3(X(i)).matrix(), atol=1e-8)


def test_custom_factor_is_a_graph_factor_with_its_keys():
    seen = []

    def error(this, values, H):
        seen.append((type(this).__name__, list(this.keys()), this.dim()))
        if H is not None:
            H[0] = np.eye(2)
        return values.atPoint2(L(1)) - np.array([3.0, 4.0])

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [L(1)], error))
    assert type(graph.at(0)).__name__ == "CustomFactor"
    assert "CustomFactor(L(1))" in repr(graph.at(0))
    values = gtsam.Values()
    values.insert(L(1), gtsam.Point2(0.0, 0.0))
    assert graph.error(values) == pytest.approx(0.5 * 25.0)
    result, summary = gtsam.solve(graph, values, method="gn")
    np.testing.assert_allclose(result.atPoint2(L(1)), [3.0, 4.0], atol=1e-12)
    assert seen[0] == ("CustomFactor", [L(1)], 2)


def test_an_exception_in_the_error_function_reaches_the_caller_unchanged():
    class Broken(Exception):
        pass

    calls = []

    def error(this, values, H):
        calls.append(H is not None)
        if H is not None:
            raise Broken("no Jacobian today")
        return values.atPoint2(L(1))

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [L(1)], error))
    values = gtsam.Values()
    values.insert(L(1), gtsam.Point2(1.0, 2.0))
    assert graph.error(values) == pytest.approx(2.5)
    with pytest.raises(Broken, match="no Jacobian today"):
        gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    # And nothing is left over for the next, healthy call.
    healthy = gtsam.NonlinearFactorGraph()
    healthy.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), ODOMETRY))
    start = gtsam.Values()
    start.insert(X(0), gtsam.Pose2(0.1, 0.0, 0.0))
    gtsam.LevenbergMarquardtOptimizer(healthy, start).optimize()


@pytest.mark.parametrize(
    "returns, jacobian, raised, message",
    [
        (np.zeros(3), np.eye(2), gtsam.DimensionMismatch, "returned 3 numbers, the noise model has dimension 2"),
        (np.zeros(2), np.eye(3), gtsam.DimensionMismatch, r"H\[0\]"),
        (np.zeros(2), None, gtsam.FactordError, r"left H\[0\] unset"),
        ("not numbers", np.eye(2), TypeError, "error function's result: not an array of numbers"),
    ],
)
def test_wrong_shapes_are_named(returns, jacobian, raised, message):
    def error(this, values, H):
        if H is not None and jacobian is not None:
            H[0] = jacobian
        return returns

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [L(1)], error))
    values = gtsam.Values()
    values.insert(L(1), gtsam.Point2(1.0, 2.0))
    with pytest.raises(raised, match=message):
        gtsam.GaussNewtonOptimizer(graph, values).optimize()


def test_bad_construction_is_refused():
    with pytest.raises(TypeError, match="callable"):
        gtsam.CustomFactor(GPS2, [X(0)], 42)
    with pytest.raises(gtsam.FactordError, match="at least one key"):
        gtsam.CustomFactor(GPS2, [], lambda t, v, H: np.zeros(2))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(GPS2, [X(5)], lambda t, v, H: np.zeros(2)))
    with pytest.raises(gtsam.ValuesKeyDoesNotExist, match="X\\(5\\)"):
        gtsam.GaussNewtonOptimizer(graph, gtsam.Values()).optimize()


def test_isam2_relinearises_python_factors_on_its_second_thread():
    # A loop closure after a long walk relinearises hundreds of factors at once, which the
    # engine does on a second thread while it orders: the error functions run there.
    n = 600
    threads = set()
    fixes = {}

    def gps(m):
        inner = gps_pose2(m)

        def error(this, values, H):
            threads.add(threading.get_ident())
            return inner(this, values, H)

        return error

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-9)
    isam = gtsam.ISAM2(params)
    step = gtsam.Pose2(1.0, 0.0, 2 * math.pi / n)
    truth = gtsam.Pose2()
    batch = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    rng = np.random.default_rng(11)
    for i in range(n):
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if i:
            graph.add(gtsam.BetweenFactorPose2(X(i - 1), X(i), step, ODOMETRY))
            truth = truth.compose(step)
        else:
            graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 10.0)))
        if i % 50 == 0:
            fixes[i] = truth.translation() + rng.normal(0, 0.3, 2)
            graph.add(gtsam.CustomFactor(GPS2, [X(i)], gps(fixes[i])))
        values.insert(X(i), gtsam.Pose2(truth.x() + 0.5, truth.y() - 0.5, truth.theta() + 0.05))
        if i == n - 1:
            graph.add(gtsam.BetweenFactorPose2(X(i), X(0), step, ODOMETRY))
        isam.update(graph, values)
        batch.push_back(graph)
        initial.insert(values)
    for _ in range(3):
        isam.update()
    streamed = isam.calculateEstimate()
    best = gtsam.LevenbergMarquardtOptimizer(batch, initial).optimize()
    assert batch.error(streamed) == pytest.approx(batch.error(best), rel=1e-6)
    assert threading.get_ident() in threads and len(threads) >= 2, threads


def test_factor_type_records_a_python_function_as_the_wire_tree():
    BeaconRange = fx.FactorType(
        "beacon_range",
        variables=[("x", "se2")],
        parameters=[("beacon", "point2"), ("range", "scalar")],
        residual=lambda x, beacon, range: fx.norm(beacon - x.translation()) - range,
    )
    # The tree is the one docs/guide/factor-types.md posts to a server.
    assert BeaconRange.definition["residual"] == {
        "sub": [{"norm": [{"sub": ["beacon", {"translation": ["x"]}]}]}, "range"]
    }
    same = gtsam.FactorType.from_definition(json.dumps(BeaconRange.definition))
    assert same.residual_dim == 1 and same.name == "beacon_range"
    # The guide's session: pose 1 ends 5 m from (1, 5) and 3 m from (4, 0), i.e. at (1, 0).
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
    graph.add(gtsam.BetweenFactorPose2(X(0), X(1), gtsam.Pose2(1, 0, 0), gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.05]))))
    beacon = gtsam.noiseModel.Isotropic.Sigma(1, 0.01)
    graph.add(BeaconRange([X(1)], [gtsam.Point2(1, 5), 5.0], beacon))
    graph.add(same(X(1), [np.array([4.0, 0.0]), 3.0], beacon))
    initial = gtsam.Values()
    initial.insert(X(0), gtsam.Pose2(0, 0, 0))
    initial.insert(X(1), gtsam.Pose2(0.9, 0.2, 0.1))
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    np.testing.assert_allclose(result.atPose2(X(1)).translation(), [1.0, 0.0], atol=1e-6)


def test_factor_type_operators_match_numpy():
    # A relative pose in se3 written with operators: log of the between, rotation first.
    Relative = fx.FactorType(
        "relative_se3",
        variables=[("a", "se3"), ("b", "se3")],
        parameters=[("z", "se3")],
        residual=lambda a, b, z: fx.vector(
            (z.inverse() * a.between(b)).rotation().log(),
            (z.inverse() * a.between(b)).translation(),
        ),
    )
    a = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, -0.1, 0.3), gtsam.Point3(1, 2, 3))
    b = gtsam.Pose3(gtsam.Rot3.Ypr(-0.4, 0.2, 0.1), gtsam.Point3(-1, 0.5, 2))
    z = gtsam.Pose3(gtsam.Rot3.Ypr(-0.5, 0.25, -0.1), gtsam.Point3(-2, -1, 0.5))
    values = gtsam.Values()
    values.insert(X(0), a)
    values.insert(X(1), b)
    factor = Relative([X(0), X(1)], [z], gtsam.noiseModel.Unit.Create(6))
    d = z.inverse().compose(a.between(b))
    rotation_log = gtsam.Pose3.Logmap(gtsam.Pose3(d.rotation(), np.zeros(3)))[:3]
    expected = np.concatenate([rotation_log, d.translation()])
    assert factor.error(values) == pytest.approx(0.5 * float(expected @ expected), rel=1e-9)


def test_factor_type_errors_name_the_node():
    with pytest.raises(gtsam.FactordError, match=r"residual\.translation: `translation` takes se2"):
        fx.FactorType("bad", variables=[("x", "point2")], residual=lambda x: x.translation())
    with pytest.raises(TypeError, match="cannot be compared"):
        fx.FactorType("branchy", variables=[("x", "point2")], residual=lambda x: x if x[0] > 0 else -x)
    with pytest.raises(TypeError, match="truth value"):
        fx.FactorType("branchy", variables=[("x", "point2")], residual=lambda x: x if x[0] else -x)
    with pytest.raises(gtsam.FactordError, match="name"):
        fx.FactorType("Bad Name", variables=[("x", "point2")], residual=lambda x: x)
    Shift = fx.FactorType("shift", variables=[("x", "point2")], parameters=[("d", "vector", 2)], residual=lambda x, d: x - d)
    with pytest.raises(gtsam.FactordError, match="0 parameters given, the type declares 1"):
        Shift([L(0)], [], gtsam.noiseModel.Unit.Create(2))
    with pytest.raises(gtsam.DimensionMismatch):
        Shift([L(0)], [np.zeros(3)], gtsam.noiseModel.Unit.Create(2))
    with pytest.raises(gtsam.DimensionMismatch):
        Shift([L(0)], [np.zeros(2)], gtsam.noiseModel.Unit.Create(3))
