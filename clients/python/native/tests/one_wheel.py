"""One wheel, both ways in: with only the ``factord`` wheel on the path, a factor type written as
a Python function is solved in process (``factord``) and, as the same definition, by a running
server through the wire client the wheel carries (``factord_client``); both reach the same
optimum. Run by tests/tools/python_native.rs with the server's URL as its argument."""

import os
import sys

import numpy as np

import factord
import factord_client
from factord import expressions as fx

SITE = os.path.dirname(os.path.dirname(factord.__file__))
assert os.path.dirname(os.path.dirname(factord_client.__file__)) == SITE, (
    "factord_client must come from the factord wheel",
    factord_client.__file__,
    SITE,
)

BeaconRange = fx.FactorType(
    "beacon_range",
    variables=[("x", "se2")],
    parameters=[("beacon", "point2"), ("range", "scalar")],
    residual=lambda x, beacon, range: fx.norm(beacon - x.translation()) - range,
)

rng = np.random.default_rng(56)
beacons = [np.array([0.0, 8.0]), np.array([9.0, 1.0]), np.array([-6.0, -5.0])]
n = 25
truth = [(0.4 * i, 0.1 * i * i / n, 0.05 * i) for i in range(n)]
odometry_sigmas = [0.05, 0.05, 0.02]
range_sigma = 0.1

# The measurements, the same for both sides.
odometry = []
for i in range(1, n):
    a = factord.Pose2(*truth[i - 1])
    b = factord.Pose2(*truth[i])
    d = a.between(b)
    odometry.append((i, [d.x() + rng.normal(0, 0.05), d.y() + rng.normal(0, 0.05), d.theta() + rng.normal(0, 0.02)]))
ranges = []
for i in range(n):
    for j, beacon in enumerate(beacons):
        r = float(np.hypot(*(beacon - np.array(truth[i][:2])))) + rng.normal(0, range_sigma)
        ranges.append((i, j, r))
start = [(x + 0.3, y - 0.2, t + 0.05) for (x, y, t) in truth]

# In process.
graph = factord.NonlinearFactorGraph()
graph.add(factord.PriorFactorPose2(0, factord.Pose2(*truth[0]), factord.noiseModel.Isotropic.Sigma(3, 1e-3)))
for i, d in odometry:
    graph.add(factord.BetweenFactorPose2(i - 1, i, factord.Pose2(*d), factord.noiseModel.Diagonal.Sigmas(np.array(odometry_sigmas))))
for i, j, r in ranges:
    graph.add(BeaconRange([i], [beacons[j], r], factord.noiseModel.Isotropic.Sigma(1, range_sigma)))
initial = factord.Values()
for i, p in enumerate(start):
    initial.insert(i, factord.Pose2(*p))
params = factord.GaussNewtonParams()
params.setRelativeErrorTol(1e-12)
here = factord.GaussNewtonOptimizer(graph, initial, params).optimize()

# On the server, the same definition through the wheel's wire client.
client = factord_client.HttpClient(sys.argv[1])
client.create_session(
    "pose_graph_2d",
    session="one-wheel",
    options={"method": "gauss_newton", "function_tolerance": 1e-12},
    auto_optimize="manual",
    factor_types=[BeaconRange.definition],
)
variables = [{"key": i, "kind": "se2", "value": list(p)} for i, p in enumerate(start)]
factors = [{"type": "prior_se2", "keys": [0], "measurement": list(truth[0]), "sigmas": [1e-3] * 3}]
factors += [{"type": "between_se2", "keys": [i - 1, i], "measurement": d, "sigmas": odometry_sigmas} for i, d in odometry]
factors += [
    {"type": "beacon_range", "keys": [i], "measurement": [*beacons[j], r], "sigmas": [range_sigma]}
    for i, j, r in ranges
]
client.apply_batch("one-wheel", {"variables": variables, "factors": factors})
client.optimize("one-wheel", wait=True)
there = client.estimate_poses("one-wheel")

worst = 0.0
for i in range(n):
    a = here.atPose2(i)
    b = there[i]
    dtheta = (a.theta() - b.theta + np.pi) % (2 * np.pi) - np.pi
    worst = max(worst, abs(a.x() - b.x), abs(a.y() - b.y), abs(dtheta))
print(f"one wheel: {n} poses, in process vs server differ by {worst:.2e}")
assert worst < 1e-8, worst
