"""factord in process (the `factord` package built from clients/python/native), without GTSAM:
keys, geometry against numpy, errors as typed exceptions naming keys as X(1), noise models, an
ISAM2 stream against the batch optimum, g2o round trips. Run by tests/tools/python_native.rs."""

import math
import os

import numpy as np
import pytest

import factord as gtsam
from factord.symbol_shorthand import L, X  # noqa: F401 (a GTSAM import shape)

DATA = os.environ.get("FACTORD_DATA", os.path.join(os.path.dirname(__file__), "../../../../../shared/data"))


def test_keys_are_gtsam_symbols():
    assert X(1) == gtsam.symbol("x", 1) == (ord("x") << 56) | 1
    assert L(3) == gtsam.symbol("l", 3)
    assert gtsam.symbolChr(X(7)) == "x" and gtsam.symbolIndex(X(7)) == 7
    assert gtsam.keyName(X(1)) == "X(1)" and gtsam.keyName(42) == "42"
    with pytest.raises(ValueError):
        gtsam.symbol("x", 1 << 56)


def test_pose2_and_pose3_match_their_matrices():
    a, b = gtsam.Pose2(1.0, 2.0, 0.3), gtsam.Pose2(-0.5, 0.7, -1.2)
    np.testing.assert_allclose(a.compose(b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    np.testing.assert_allclose(a.between(b).matrix(), np.linalg.inv(a.matrix()) @ b.matrix(), atol=1e-12)
    np.testing.assert_allclose((a * b).translation(), a.transformFrom(b.translation()), atol=1e-12)
    assert isinstance(a.translation(), np.ndarray)
    assert a.equals(gtsam.Pose2.Expmap(gtsam.Pose2.Logmap(a)), 1e-12)
    r = gtsam.Rot3.Ypr(0.3, -0.2, 0.1)
    p = gtsam.Pose3(r, gtsam.Point3(1, 2, 3))
    q = gtsam.Pose3(gtsam.Rot3.Rx(0.4), np.array([0.0, -1.0, 2.0]))
    np.testing.assert_allclose(p.compose(q).matrix(), p.matrix() @ q.matrix(), atol=1e-12)
    np.testing.assert_allclose(p.inverse().matrix(), np.linalg.inv(p.matrix()), atol=1e-12)
    np.testing.assert_allclose(r.ypr(), [0.3, -0.2, 0.1], atol=1e-12)
    xi = np.array([0.1, -0.2, 0.3, 1.0, 2.0, -0.5])  # rotation first, as GTSAM
    np.testing.assert_allclose(gtsam.Pose3.Logmap(gtsam.Pose3.Expmap(xi)), xi, atol=1e-12)
    np.testing.assert_allclose(gtsam.Pose3.Expmap(np.r_[xi[:3], 0, 0, 0]).rotation().matrix(),
                               gtsam.Rot3.Expmap(xi[:3]).matrix(), atol=1e-12)
    np.testing.assert_allclose(gtsam.Pose3(p.matrix()).matrix(), p.matrix(), atol=1e-12)


def small_graph():
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2, 0.2, 0.1]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(1), gtsam.Pose2(0, 0, 0), noise))
    graph.add(gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), noise))
    values = gtsam.Values()
    values.insert(X(1), gtsam.Pose2(0.1, 0, 0))
    values.insert(X(2), gtsam.Pose2(2.2, 0.1, 0))
    return graph, values, noise


def test_a_missing_key_is_named_as_gtsam_writes_it():
    graph, values, _ = small_graph()
    with pytest.raises(gtsam.ValuesKeyDoesNotExist, match=r"X\(3\)"):
        values.atPose2(X(3))
    graph.add(gtsam.BetweenFactorPose2(X(2), X(3), gtsam.Pose2(1, 0, 0), gtsam.noiseModel.Unit.Create(3)))
    with pytest.raises(gtsam.ValuesKeyDoesNotExist, match=r"X\(3\)"):
        gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    with pytest.raises(gtsam.ValuesKeyDoesNotExist, match=r"X\(3\)"):
        graph.error(values)
    assert issubclass(gtsam.ValuesKeyDoesNotExist, gtsam.FactordError)
    assert issubclass(gtsam.FactordError, RuntimeError)


def test_a_wrong_type_is_refused_naming_the_key():
    graph, values, noise = small_graph()
    with pytest.raises(gtsam.ValuesIncorrectType, match=r"X\(1\) is a Pose2, not a Pose3"):
        values.atPose3(X(1))
    values.insert(L(1), gtsam.Point2(1, 2))
    graph.add(gtsam.BetweenFactorPose2(X(2), L(1), gtsam.Pose2(), noise))
    with pytest.raises(gtsam.ValuesIncorrectType, match=r"L\(1\) is a Point2"):
        gtsam.GaussNewtonOptimizer(graph, values).optimize()
    with pytest.raises(gtsam.ValuesIncorrectType):
        values.update(X(1), gtsam.Point2(0, 0))
    with pytest.raises(gtsam.ValuesIncorrectType):
        values.insert(X(9), "not a value")
    with pytest.raises(gtsam.ValuesKeyAlreadyExists, match=r"X\(1\)"):
        values.insert(X(1), gtsam.Pose2())
    with pytest.raises(TypeError):
        values.atPose2("x1")


def test_a_noise_model_of_the_wrong_dimension_is_refused():
    with pytest.raises(gtsam.DimensionMismatch, match="dimension 2.*has 3"):
        gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(2, 0.1))
    with pytest.raises(gtsam.DimensionMismatch):
        gtsam.PriorFactorPose3(X(1), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas([0.1, 0.1, 0.1]))
    with pytest.raises(gtsam.InvalidNoiseModel):
        gtsam.noiseModel.Diagonal.Sigmas([0.1, 0.0, 0.1])
    with pytest.raises(gtsam.InvalidNoiseModel):
        gtsam.noiseModel.Gaussian.Covariance(np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(gtsam.DimensionMismatch):
        gtsam.noiseModel.Gaussian.Covariance(np.ones((2, 3)))


def test_an_unconstrained_graph_is_an_indeterminant_system():
    graph, values, noise = small_graph()
    free = gtsam.NonlinearFactorGraph()
    free.add(graph.at(1))  # the between factor alone: the pair can slide
    with pytest.raises(gtsam.IndeterminantLinearSystemException, match=r"X\([12]\)"):
        gtsam.GaussNewtonOptimizer(free, values).optimize()
    with pytest.raises(gtsam.IndeterminantLinearSystemException):
        gtsam.Marginals(free, values)


def test_noise_models_weigh_as_gtsam_does():
    graph, values, _ = small_graph()
    f = gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), gtsam.noiseModel.Isotropic.Sigma(3, 0.5))
    # X(2) is 0.2 off in x and 0.1 in y from X(1) ⊕ (2, 0, 0): ½ ‖e / σ‖².
    expected = 0.5 * (0.1 ** 2 + 0.1 ** 2) / 0.25
    assert f.error(values) == pytest.approx(expected, rel=1e-12)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.0], [0.0, 0.0, 0.01]])
    g = gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), gtsam.noiseModel.Gaussian.Covariance(cov))
    e = np.array([0.1, 0.1, 0.0])
    assert g.error(values) == pytest.approx(0.5 * e @ np.linalg.solve(cov, e), rel=1e-12)
    np.testing.assert_allclose(g.noiseModel().covariance(), cov, atol=1e-15)
    # Huber on the whitened norm x = ‖e/σ‖: k|x| − k²/2 beyond k.
    k = 0.1
    huber = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k),
                                           gtsam.noiseModel.Isotropic.Sigma(3, 0.5))
    h = gtsam.BetweenFactorPose2(X(1), X(2), gtsam.Pose2(2, 0, 0), huber)
    x = math.sqrt(2 * expected)
    assert h.error(values) == pytest.approx(k * x - k * k / 2, rel=1e-12)
    assert huber.isRobust()


def stream(n=60, seed=3):
    """A square-ish walk with noisy odometry and loop closures: (steps, noise) where each step is
    (key, initial guess, [factors])."""
    rng = np.random.RandomState(seed)
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
    truth = [gtsam.Pose2(0, 0, 0)]
    for i in range(1, n):
        turn = math.pi / 2 if i % 10 == 0 else 0.0
        truth.append(truth[-1].compose(gtsam.Pose2(1.0, 0.0, turn)))
    steps = [(X(0), truth[0], [gtsam.PriorFactorPose2(X(0), truth[0], gtsam.noiseModel.Isotropic.Sigma(3, 1e-3))])]
    estimate = truth[0]
    for i in range(1, n):
        z = truth[i - 1].between(truth[i]).compose(gtsam.Pose2(*rng.normal(0, [0.05, 0.05, 0.02])))
        factors = [gtsam.BetweenFactorPose2(X(i - 1), X(i), z, odo)]
        for j in range(0, i - 5):
            if truth[i].range(truth[j].translation()) < 0.5 and rng.rand() < 0.7:
                c = truth[j].between(truth[i]).compose(gtsam.Pose2(*rng.normal(0, [0.05, 0.05, 0.02])))
                factors.append(gtsam.BetweenFactorPose2(X(j), X(i), c, odo))
        estimate = estimate.compose(z)
        steps.append((X(i), estimate, factors))
    return steps


def run_stream(threshold):
    """The stream through ISAM2 update by update (then three empty updates, as a GTSAM user
    settles an estimate); the incremental estimate, and the whole graph and initial values."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(threshold)
    isam = gtsam.ISAM2(params)
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    closures = 0
    for key, guess, factors in stream():
        new_graph, new_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        new_values.insert(key, guess)
        initial.insert(key, guess)
        for f in factors:
            new_graph.add(f)
            graph.add(f)
        closures += len(factors) - 1
        isam.update(new_graph, new_values)
        assert isam.calculateEstimate().size() == initial.size()
    assert closures >= 5, closures
    for _ in range(3):
        isam.update()
    assert isam.getFactorsUnsafe().size() == graph.size()
    return isam, graph, initial


def test_isam2_update_by_update_reaches_the_batch_optimum():
    params_lm = gtsam.LevenbergMarquardtParams()
    params_lm.setRelativeErrorTol(1e-12)
    isam, graph, initial = run_stream(1e-6)
    batch = gtsam.LevenbergMarquardtOptimizer(graph, initial, params_lm).optimize()
    incremental = isam.calculateEstimate()
    a, b = gtsam.utilities.extractPose2(incremental), gtsam.utilities.extractPose2(batch)
    diff = np.abs(a - b).max()
    print(f"ISAM2 (threshold 1e-6) vs batch: max pose difference {diff:.2e}, errors "
          f"{graph.error(incremental):.10f} {graph.error(batch):.10f}")
    assert diff < 1e-6
    assert graph.error(incremental) == pytest.approx(graph.error(batch), rel=1e-9)
    np.testing.assert_allclose(isam.marginalCovariance(X(5)),
                               gtsam.Marginals(graph, batch).marginalCovariance(X(5)), rtol=1e-5, atol=1e-12)
    # GTSAM's default threshold (0.1) relinearises less and stops near the optimum, as GTSAM's does.
    loose, _, _ = run_stream(0.1)
    gap = graph.error(loose.calculateEstimate()) / graph.error(batch) - 1
    print(f"ISAM2 (threshold 0.1): error {gap:.1e} relative above the batch optimum")
    assert 0 <= gap < 1e-2


def test_isam2_refuses_a_factor_on_an_unknown_variable_and_keeps_going():
    isam = gtsam.ISAM2()
    graph, values, noise = small_graph()
    isam.update(graph, values)
    bad = gtsam.NonlinearFactorGraph()
    bad.add(gtsam.BetweenFactorPose2(X(2), X(3), gtsam.Pose2(1, 0, 0), noise))
    with pytest.raises(gtsam.ValuesKeyDoesNotExist, match=r"X\(3\)"):
        isam.update(bad, gtsam.Values())
    more = gtsam.Values()
    more.insert(X(3), gtsam.Pose2(3.1, 0, 0))
    isam.update(bad, more)
    assert isam.calculateEstimatePose2(X(3)).x() == pytest.approx(3.0, abs=1e-6)


def test_read_and_write_g2o_round_trip(tmp_path):
    path = os.path.join(DATA, "2d/carlone/input_INTEL_g2o.g2o")
    graph, initial = gtsam.readG2o(path, False)
    assert initial.size() == 1228 and graph.size() == 1483
    assert isinstance(graph.at(0), gtsam.BetweenFactorPose2)
    with pytest.raises(gtsam.FactordError, match="2D"):
        gtsam.readG2o(path, True)
    out = tmp_path / "intel.g2o"
    gtsam.writeG2o(graph, initial, str(out))
    again, values = gtsam.readG2o(str(out), False)
    assert again.size() == graph.size() and values.size() == initial.size()
    assert again.error(values) == pytest.approx(graph.error(initial), rel=1e-12)
    # factord's own call returns the Summary `factord solve` prints.
    estimate, summary = gtsam.solve(graph, initial, method="gauss_newton", initialization="auto")
    assert summary["converged"], summary["termination"]
    assert 2 * graph.error(estimate) == pytest.approx(summary["final_chi2"], rel=1e-9)
    print(f"intel in process: final chi2 {summary['final_chi2']:.6f}, {summary['solve_seconds'] * 1e3:.1f} ms")


def test_the_readme_example_runs(tmp_path):
    import subprocess
    import sys

    example = os.path.join(os.path.dirname(__file__), "../examples/pose_graph.py")
    out = tmp_path / "m3500.g2o"
    run = subprocess.run([sys.executable, example, os.path.join(DATA, "2d/carlone/input_M3500_g2o.g2o"), str(out)],
                         capture_output=True, text=True, check=True)
    print(run.stdout)
    assert "error 20.109 -> " in run.stdout  # Pose2SLAMExample
    assert "-> 68.9564" in run.stdout  # M3500's optimum (chi2 137.91295, as `factord solve`)
    assert "ISAM2 stream: 3500 updates" in run.stdout
    graph, values = gtsam.readG2o(str(out), False)
    assert values.size() == 3500 and graph.size() == 5453  # the prior is written as a comment


def test_bad_input_raises_and_never_brings_the_process_down():
    # Each of these once could, or would in a careless binding: an allocation of dimension²
    # doubles, a NaN through the solver, a missing file, a points query of another width.
    with pytest.raises(gtsam.DimensionMismatch, match="from 1 to 1000"):
        gtsam.noiseModel.Isotropic.Sigma(10**12, 1.0)
    with pytest.raises(gtsam.DimensionMismatch):
        gtsam.noiseModel.Diagonal.Sigmas(np.ones(10**4))
    values, graph = gtsam.Values(), gtsam.NonlinearFactorGraph()
    values.insert(X(1), gtsam.Pose2())
    graph.add(gtsam.PriorFactorPose2(X(1), gtsam.Pose2(float("nan"), 0, 0), gtsam.noiseModel.Unit.Create(3)))
    with pytest.raises(gtsam.FactordError, match="non-finite"):
        gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    with pytest.raises(gtsam.FactordError, match="cannot read"):
        gtsam.readG2o("/nonexistent/graph.g2o")
    with pytest.raises(ValueError):
        values._point_rows(5)
    with pytest.raises(gtsam.FactordError, match="twice"):
        graph2 = gtsam.NonlinearFactorGraph()
        graph2.add(gtsam.BetweenFactorPose2(X(1), X(1), gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3)))
        gtsam.GaussNewtonOptimizer(graph2, values)
    assert gtsam.ISAM2().update() is not None  # an empty first update


def test_point_factors_solve_a_linear_problem_as_numpy_does():
    # Landmarks tied by priors and differences only: a linear least-squares problem, whose
    # solution numpy gives directly. Gauss-Newton reaches it only with exact Jacobians.
    rng = np.random.default_rng(5)
    n = 6
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5, 2.0]))
    between = gtsam.noiseModel.Isotropic.Sigma(2, 0.1)
    graph = gtsam.NonlinearFactorGraph()
    rows, rhs = [], []
    for i in (0, n - 1):
        p = rng.normal(0, 3, 2)
        graph.add(gtsam.PriorFactorPoint2(L(i), p, prior))
        for d, s in enumerate((0.5, 2.0)):
            row = np.zeros(2 * n)
            row[2 * i + d] = 1 / s
            rows.append(row)
            rhs.append(p[d] / s)
    differences = []
    for i in range(n - 1):
        d = rng.normal(0, 1, 2)
        differences.append(d)
        graph.add(gtsam.BetweenFactorPoint2(L(i), L(i + 1), d, between))
        for k in range(2):
            row = np.zeros(2 * n)
            row[2 * (i + 1) + k], row[2 * i + k] = 10.0, -10.0
            rows.append(row)
            rhs.append(10.0 * d[k])
    initial = gtsam.Values()
    for i in range(n):
        initial.insert(L(i), gtsam.Point2(*rng.normal(0, 5, 2)))
    result = gtsam.GaussNewtonOptimizer(graph, initial).optimize()
    expected = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0].reshape(n, 2)
    np.testing.assert_allclose(gtsam.utilities.extractPoint2(result), expected, atol=1e-9)
    assert isinstance(graph.at(0), gtsam.PriorFactorPoint2)
    assert isinstance(graph.at(2), gtsam.BetweenFactorPoint2)
    np.testing.assert_allclose(graph.at(2).measured(), differences[0])
    # The 3D twins.
    graph3 = gtsam.NonlinearFactorGraph()
    graph3.add(gtsam.PriorFactorPoint3(L(0), gtsam.Point3(1, 2, 3), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    graph3.add(gtsam.BetweenFactorPoint3(L(0), L(1), gtsam.Point3(0.5, -1, 2), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    start = gtsam.Values()
    start.insert(L(0), gtsam.Point3(0, 0, 0))
    start.insert(L(1), gtsam.Point3(0, 0, 0))
    r3 = gtsam.GaussNewtonOptimizer(graph3, start).optimize()
    np.testing.assert_allclose(r3.atPoint3(L(1)), [1.5, 1.0, 5.0], atol=1e-12)
    with pytest.raises(gtsam.DimensionMismatch):
        gtsam.PriorFactorPoint2(L(0), gtsam.Point3(1, 2, 3), prior)


def test_bearing_only_sightings_place_a_landmark():
    # Three poses see one landmark at (4, 3) by bearing only; from a wrong start it ends there.
    landmark = np.array([4.0, 3.0])
    poses = [gtsam.Pose2(0, 0, 0.1), gtsam.Pose2(2, -1, 1.0), gtsam.Pose2(6, 0, 2.0)]
    tight = gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)
    sigma = gtsam.noiseModel.Isotropic.Sigma(1, 0.01)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for i, p in enumerate(poses):
        graph.add(gtsam.PriorFactorPose2(X(i), p, tight))
        seen = math.atan2(landmark[1] - p.y(), landmark[0] - p.x()) - p.theta()
        graph.add(gtsam.BearingFactor2D(X(i), L(0), gtsam.Rot2(seen), sigma))
        initial.insert(X(i), p)
    initial.insert(L(0), gtsam.Point2(3.0, 5.0))
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    np.testing.assert_allclose(result.atPoint2(L(0)), landmark, atol=1e-6)
    assert isinstance(graph.at(1), gtsam.BearingFactor2D)
    assert graph.at(1).measured().theta() == pytest.approx(math.atan2(3.0, 4.0) - 0.1)


def test_gps_and_pose_to_point_factors_place_a_trajectory_and_a_landmark():
    # GPS fixes (at the origin and on a lever arm) and a landmark seen as body-frame positions,
    # all exact: the optimum is the truth, and each factor's error there is zero.
    step = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.0, 0.0), gtsam.Point3(1.0, 0.0, 0.0))
    arm = gtsam.Point3(0.2, 0.1, 0.8)
    mark = gtsam.Point3(2.0, 3.0, 1.0)
    truth = [gtsam.Pose3()]
    for _ in range(5):
        truth.append(truth[-1].compose(step))
    fix = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for i, p in enumerate(truth):
        if i % 2:
            graph.add(gtsam.GPSFactorArm(X(i), p.transformFrom(arm), arm, fix))
        else:
            graph.add(gtsam.GPSFactor(X(i), p.translation(), fix))
        if i:
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, gtsam.noiseModel.Isotropic.Sigma(6, 0.05)))
        graph.add(gtsam.PoseToPointFactor3D(X(i), L(0), p.transformTo(mark), fix))
        initial.insert(X(i), p.retract(np.array([0.05, -0.03, 0.02, 0.3, -0.2, 0.1])))
    initial.insert(L(0), gtsam.Point3(1.0, 1.0, 0.0))
    assert graph.at(1).error(initial) > 0
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    for i, p in enumerate(truth):
        assert result.atPose3(X(i)).equals(p, 1e-6)
    np.testing.assert_allclose(result.atPoint3(L(0)), mark, atol=1e-6)
    assert graph.error(result) < 1e-12
    assert isinstance(graph.at(0), gtsam.GPSFactor)


def test_bundle_adjustment_in_process_reaches_the_ceres_optimum():
    path = os.path.join(DATA, "bal/problem-49-7776-pre.txt")
    if not os.path.exists(path):
        pytest.skip(f"{path} missing")
    graph, initial = gtsam.loadBal(path)
    assert (graph.size(), initial.size()) == (31843, 49 + 7776)
    # BAL's cost convention (½Σ‖e‖²) is graph.error: MANIFEST's initial cost.
    assert graph.error(initial) == pytest.approx(850912.5, rel=1e-6)
    first = graph.at(0)
    assert isinstance(first, gtsam.SnavelyReprojectionFactor) and first.keys() == [0, 49]
    camera = initial.atSnavelyCamera(0)
    assert gtsam.SnavelyCamera.fromBal(camera.bal()).equals(camera, 1e-12)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    # Ceres' optimum (tests/library/bal.rs), through the Schur complement of the points.
    assert optimizer.error() == pytest.approx(13344.32, rel=1e-3)
    assert optimizer.summary()["used"]["schur"]["eliminated_variables"] == 7776
    # The camera's projection is the factor's model: its error is ½‖projection − measured‖².
    seen = result.atSnavelyCamera(0).project(result.atPoint3(49))
    assert first.error(result) == pytest.approx(0.5 * float(np.sum((seen - first.measured()) ** 2)), rel=1e-12)
    with pytest.raises(gtsam.DimensionMismatch):
        gtsam.SnavelyCamera(gtsam.Rot3(), np.zeros(2), 500.0)
