#!/usr/bin/env python3
"""GTSAM's fixed-lag smoother on a fusion inputs file (`factord fusion-eval --inputs-out FILE`),
fed as a robot would: IMU samples and keyframes in time order,
one smoother update per keyframe. Records the newest keyframe's pose right after its update and
prints JSON with the trajectory, evo-style APE statistics and the update times.

    PY=~/.cache/factord/venvs/gtsam/bin/python
    $PY benches/fusion/gtsam_fixed_lag.py INPUTS.json [--smoother incremental|batch]
        [--error-mode componentwise|logmap] [--preint-bias latest|predicted]
        [--factorization cholesky|qr] [--tum-out FILE] [--marginals-out FILE] [--summary-only]
        [--compact]

Model (GTSAM 4.3.0 Python; see GTSAM_PREINTEGRATION.md):
* use_imu: keys X(k) Pose3, V(k) Vector3 (world), B(k) imuBias.ConstantBias per keyframe;
  PreintegratedCombinedMeasurements (tangent backend) on PreintegrationCombinedParams.MakeSharedU(g),
  all five covariances set from the continuous-time densities (squared, not discretised);
  CombinedImuFactor(X(k-1), V(k-1), X(k), V(k), B(k-1), B(k)) (bias random walk inside).
  Samples are held (zero-order hold) until the next sample; a keyframe at t closes the
  pre-integration with the last sample held up to t, and the next one starts at t with that
  sample. The pre-integration of (k-1, k] uses the bias estimate of B(k-1) right after update
  k-1 (`--preint-bias latest`, GTSAM's usual reset) or B(k-1)'s initial value, i.e. B(k-2)'s
  estimate after update k-2 (`--preint-bias predicted`, what src/fusion/window.rs does).
  New keyframe initial values: pim.predict(NavState(X, V), B) from the previous estimates; B(k) = B(k-1).
* not use_imu: Pose3 keys only; initial value = previous estimate composed with the relative pose.
* Relative poses: BetweenFactorPose3 with Diagonal.Sigmas([sr]*3 + [sp]*3) (Pose3 tangent is
  [rotation, translation]); pose priors: PriorFactorPose3 likewise; initial priors on X0, V0, B0.
* Smoother lag: the smoother marginalises keys whose timestamp < t_newest - lag, after the
  optimisation of that update (both smoothers: optimise, then marginalise). Keeping `window`
  keyframes after the update (window + 1 during its solve, as our SlidingWindow::optimize) needs
  (window - 1)/hz <= lag < window/hz; we take lag = (window - 1 + 0.5)/keyframe_hz, the middle of
  that interval: any jitter of the keyframe stamps (here +-1.5e-7 s, from the f64 ground-truth
  stamps) or of keyframe_hz then leaves the kept count at exactly `window` (the JSON reports it).
* Timing (solve_ms): the smoother.update() call(s) of each keyframe only (optimise + marginalise),
  not building factors or pre-integrating.
* --factorization qr: Cholesky (GTSAM's default, both smoothers) throws IndeterminantLinearSystem
  when there are no pose priors with the IMU on (the global position/yaw information decays while
  the bias random-walk information is ~1e10); QR gets through. On a throw the JSON has "failed"
  and statistics up to that keyframe, exit status 2.
"""
import argparse
import json
import math
import sys
import time

import numpy as np

import gtsam
from gtsam.symbol_shorthand import B, V, X


# ----------------------------------------------------------------------------------- geometry
def rot3_from_xyzw(q):
    q = np.asarray(q, float)
    n = np.linalg.norm(q)
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"bad quaternion {q}")
    x, y, z, w = q / n  # Rot3.Quaternion assumes a unit quaternion
    return gtsam.Rot3.Quaternion(w, x, y, z)


def pose3(position, rotation_xyzw):
    return gtsam.Pose3(rot3_from_xyzw(rotation_xyzw), np.asarray(position, float))


def xyzw_from_rot3(R):
    q = R.toQuaternion()
    v = np.array([q.x(), q.y(), q.z(), q.w()])
    v /= np.linalg.norm(v)
    return [float(c) for c in (-v if v[3] < 0 else v)]


def matrix4(position, rotation_xyzw):
    return pose3(position, rotation_xyzw).matrix()


def pose_noise(sigma_position, sigma_rotation):
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_rotation] * 3 + [sigma_position] * 3, float))


# ----------------------------------------------------------------------------------- statistics
def statistics(errors):
    """evo's APE statistics (std: numpy population std, as evo)."""
    e = np.asarray(errors, float)
    if e.size == 0:
        return {k: float("nan") for k in ("max", "mean", "median", "min", "rmse", "sse", "std")}
    return {
        "max": float(np.max(e)),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "min": float(np.min(e)),
        "rmse": float(math.sqrt(np.mean(e * e))),
        "sse": float(np.sum(e * e)),
        "std": float(np.std(e)),
    }


def ape(inputs, trajectory):
    truth = {k["key"]: k["truth"] for k in inputs["keyframes"]}
    full, trans = [], []
    for e in trajectory:
        t = truth.get(e["key"])
        if t is None:
            continue
        Tt = matrix4(t["position"], t["rotation_xyzw"])
        Te = matrix4(e["position"], e["rotation_xyzw"])
        E = np.linalg.inv(Tt) @ Te
        full.append(float(np.linalg.norm(E - np.eye(4), "fro")))  # evo -r full
        trans.append(float(np.linalg.norm(np.asarray(e["position"]) - np.asarray(t["position"]))))  # -r trans_part
    return statistics(full), statistics(trans)


# ----------------------------------------------------------------------------------- smoother
def make_smoother(kind, lag, args):
    if kind == "incremental":
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(args.relinearize_threshold)
        p.relinearizeSkip = args.relinearize_skip
        p.setFactorization({"cholesky": "CHOLESKY", "qr": "QR"}[args.factorization])
        return gtsam.IncrementalFixedLagSmoother(lag, p)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(args.lm_max_iterations)
    lm.setLinearSolverType({"cholesky": "MULTIFRONTAL_CHOLESKY", "qr": "MULTIFRONTAL_QR"}[args.factorization])
    return gtsam.BatchFixedLagSmoother(lag, lm)


def imu_params(inputs, error_mode):
    n = inputs["imu_noise"]
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(float(inputs["gravity"]))
    I3 = np.eye(3)
    # Continuous-time densities, squared; GTSAM applies /dt and *dt itself. Unset ones default to I.
    p.setAccelerometerCovariance(n["accel_noise_density"] ** 2 * I3)
    p.setGyroscopeCovariance(n["gyro_noise_density"] ** 2 * I3)
    p.setIntegrationCovariance(n.get("integration_sigma", 1e-4) ** 2 * I3)
    p.setBiasAccCovariance(n["accel_random_walk"] ** 2 * I3)
    p.setBiasOmegaCovariance(n["gyro_random_walk"] ** 2 * I3)
    p.setImuFactorErrorMode({"componentwise": gtsam.ImuFactorErrorMode.ComponentWise,
                             "logmap": gtsam.ImuFactorErrorMode.Logmap}[error_mode])
    return p


def run(inputs, args):
    use_imu = bool(inputs.get("use_imu", True))
    window = int(inputs["window"])
    hz = float(inputs["keyframe_hz"])
    if window < 2:
        raise ValueError(f"window must be >= 2, got {window}")
    lag = args.lag if args.lag is not None else (window - 1 + args.lag_margin) / hz
    smoother = make_smoother(args.smoother, lag, args)
    params = imu_params(inputs, args.error_mode) if use_imu else None

    ini = inputs["initial"]
    s = ini["sigmas"]
    k0, t0 = int(ini["key"]), float(ini["t"])
    pose0 = pose3(ini["position"], ini["rotation_xyzw"])
    vel0 = np.asarray(ini["velocity"], float)
    bias0 = gtsam.imuBias.ConstantBias(np.asarray(ini["accel_bias"], float), np.asarray(ini["gyro_bias"], float))

    graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    graph.add(gtsam.PriorFactorPose3(X(k0), pose0, pose_noise(s["position"], s["rotation"])))
    values.insert(X(k0), pose0)
    stamps[X(k0)] = t0
    if use_imu:
        graph.add(gtsam.PriorFactorVector(V(k0), vel0, gtsam.noiseModel.Isotropic.Sigma(3, s["velocity"])))
        graph.add(gtsam.PriorFactorConstantBias(B(k0), bias0, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([s["accel_bias"]] * 3 + [s["gyro_bias"]] * 3, float))))
        values.insert(V(k0), vel0)
        values.insert(B(k0), bias0)
        stamps[V(k0)] = t0
        stamps[B(k0)] = t0
    # Measurements by the keyframe at which a robot has them (the later keyframe of a relative pose).
    keyframes = sorted(inputs["keyframes"], key=lambda k: k["t"])
    time_of = {k0: t0, **{int(k["key"]): float(k["t"]) for k in keyframes}}
    rel_at, prior_at = {}, {}
    for r in inputs.get("relative_poses", []):
        later = max((int(r["from"]), int(r["to"])), key=lambda k: time_of[k])
        rel_at.setdefault(later, []).append(r)
    for p in inputs.get("pose_priors", []):
        prior_at.setdefault(int(p["key"]), []).append(p)
    for p in prior_at.pop(k0, []):  # a pose prior on the initial keyframe
        graph.add(gtsam.PriorFactorPose3(X(k0), pose3(p["position"], p["rotation_xyzw"]),
                                         pose_noise(p["sigma_position"], p["sigma_rotation"])))
    smoother.update(graph, values, stamps)
    for _ in range(args.extra_updates):
        smoother.update()

    imu = inputs.get("imu", []) if use_imu else []
    next_sample = 0
    last = None  # (t, acc, gyro) of the last sample received, held until the next one
    prev_key, prev_t = k0, t0
    prev_pose, prev_vel, prev_bias = pose0, vel0, bias0
    prev_bias_initial = bias0  # B(prev)'s initial value (= B(prev-1)'s estimate when it was created)
    in_window = {k0}
    trajectory, solve_ms, kept, iterations = [], [], [], []
    last_estimate = {}  # key -> its estimate at the last update it was in the smoother
    failure = None

    for kf in keyframes:
        key, t = int(kf["key"]), float(kf["t"])
        if not t > prev_t:
            raise ValueError(f"keyframe {key} at t={t} is not after the previous keyframe (t={prev_t})")
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        if use_imu:
            pim_bias = prev_bias if args.preint_bias == "latest" else prev_bias_initial
            pim = gtsam.PreintegratedCombinedMeasurements(params, pim_bias)
            # Zero-order hold: sample j covers [max(t_j, t_prev_kf), min(t_{j+1}, t)].
            while next_sample < len(imu) and imu[next_sample][0] <= t:
                smp = imu[next_sample]
                if last is not None:
                    if not smp[0] > last[0]:
                        raise ValueError(f"IMU sample at t={smp[0]} is not after t={last[0]}")
                    start = max(last[0], prev_t)
                    if smp[0] > start:
                        pim.integrateMeasurement(last[1], last[2], smp[0] - start)
                last = (float(smp[0]), np.asarray(smp[1:4], float), np.asarray(smp[4:7], float))
                next_sample += 1
            if last is not None:
                start = max(last[0], prev_t)
                if t > start:
                    pim.integrateMeasurement(last[1], last[2], t - start)
            if pim.deltaTij() <= 0.0:
                raise ValueError(f"keyframe {key} at t={t}: no IMU sample to integrate since t={prev_t}")
            graph.add(gtsam.CombinedImuFactor(X(prev_key), V(prev_key), X(key), V(key), B(prev_key), B(key), pim))
            nav = pim.predict(gtsam.NavState(prev_pose, prev_vel), prev_bias)
            guess_pose, guess_vel = nav.pose(), nav.velocity()
            values.insert(X(key), guess_pose)
            values.insert(V(key), guess_vel)
            values.insert(B(key), prev_bias)
            stamps.update({X(key): t, V(key): t, B(key): t})
            prev_bias_initial = prev_bias
        else:
            guess_pose = prev_pose
            for r in rel_at.get(key, []):
                if int(r["to"]) == key and int(r["from"]) == prev_key:
                    guess_pose = prev_pose.compose(pose3(r["position"], r["rotation_xyzw"]))
                    break
            values.insert(X(key), guess_pose)
            stamps[X(key)] = t
        in_window.add(key)
        for r in rel_at.get(key, []):
            a, b = int(r["from"]), int(r["to"])
            for k in (a, b):
                if k not in in_window:
                    raise ValueError(f"relative pose {a}-{b}: keyframe {k} is not in the window")
            graph.add(gtsam.BetweenFactorPose3(X(a), X(b), pose3(r["position"], r["rotation_xyzw"]),
                                               pose_noise(r["sigma_position"], r["sigma_rotation"])))
        for p in prior_at.get(key, []):
            kp = int(p["key"])
            if kp not in in_window:
                raise ValueError(f"pose prior on keyframe {kp}: not in the window")
            graph.add(gtsam.PriorFactorPose3(X(kp), pose3(p["position"], p["rotation_xyzw"]),
                                             pose_noise(p["sigma_position"], p["sigma_rotation"])))

        start_clock = time.perf_counter()
        try:
            res = smoother.update(graph, values, stamps)
            its = res.getIterations()
            for _ in range(args.extra_updates):
                its += smoother.update().getIterations()
        except RuntimeError as e:  # e.g. GTSAM's IndeterminantLinearSystemException
            message = " ".join(str(e).split())
            failure = {"key": key, "t": t, "error": message[:300]}
            break
        solve_ms.append((time.perf_counter() - start_clock) * 1e3)
        iterations.append(its)

        est_pose = smoother.calculateEstimatePose3(X(key))
        if use_imu:
            prev_vel = np.asarray(smoother.calculateEstimateVector(V(key)), float).reshape(3)
            prev_bias = smoother.calculateEstimateConstantBias(B(key))
        prev_pose, prev_key, prev_t = est_pose, key, t
        remaining = {gtsam.Symbol(k).index() for k in smoother.timestamps().keys()
                     if chr(gtsam.Symbol(k).chr()) == "x"}
        # Lag-smoothed: every keyframe's estimate at the last update it was still in the
        # smoother (outside the timed update, like the real-time estimate above).
        for k in remaining:
            p = est_pose if k == key else smoother.calculateEstimatePose3(X(k))
            last_estimate[k] = {"key": k, "position": [float(c) for c in p.translation()],
                                "rotation_xyzw": xyzw_from_rot3(p.rotation())}
        in_window &= remaining
        kept.append(len(remaining))
        entry = {"key": key, "t": t, "position": [float(c) for c in est_pose.translation()],
                 "rotation_xyzw": xyzw_from_rot3(est_pose.rotation()), "solve_ms": solve_ms[-1],
                 "iterations": iterations[-1]}
        if use_imu:
            entry["velocity"] = [float(c) for c in prev_vel]
            entry["accel_bias"] = [float(c) for c in prev_bias.accelerometer()]
            entry["gyro_bias"] = [float(c) for c in prev_bias.gyroscope()]
        trajectory.append(entry)
    smoothed = [last_estimate[k] for k in sorted(last_estimate)]
    if args.marginals_out and failure is None:
        write_marginals(args.marginals_out, smoother, sorted(in_window), use_imu)
    return lag, trajectory, smoothed, solve_ms, kept, iterations, failure


def write_marginals(path, smoother, keys, use_imu):
    """The marginal covariances of the keyframes left in the smoother after its last update, in
    GTSAM's tangent orders: X Pose3 [rotation, translation] (both in the body frame), V Vector3
    (world), B ConstantBias [accelerometer, gyroscope]; with each pose's rotation matrix, which
    maps GTSAM's body-frame translation to a world-frame one (benches/fusion/marginals_compare.py)."""
    out = []
    for k in keys:
        entry = {"key": int(k),
                 "rotation": np.asarray(smoother.calculateEstimatePose3(X(k)).rotation().matrix()).tolist(),
                 "pose": np.asarray(smoother.marginalCovariance(X(k))).tolist()}
        if use_imu:
            entry["velocity"] = np.asarray(smoother.marginalCovariance(V(k))).tolist()
            entry["bias"] = np.asarray(smoother.marginalCovariance(B(k))).tolist()
        out.append(entry)
    with open(path, "w") as f:
        json.dump(out, f)


def write_tum(path, inputs, trajectory):
    origin = inputs.get("origin", 0)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for e in trajectory:
            x, y, z = e["position"]
            qx, qy, qz, qw = e["rotation_xyzw"]
            f.write(f"{origin + e['t']:.6f} {x:.9f} {y:.9f} {z:.9f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", help="inputs JSON file ('-' for stdin)")
    ap.add_argument("--smoother", choices=["incremental", "batch"], default="incremental",
                    help="IncrementalFixedLagSmoother (iSAM2) or BatchFixedLagSmoother (LM)")
    ap.add_argument("--error-mode", choices=["componentwise", "logmap"], default="componentwise",
                    help="CombinedImuFactor residual: ComponentWise = Forster/GTSAM<=4.2 (closest to ours), "
                         "Logmap = GTSAM 4.3's default SE2(3) log")
    ap.add_argument("--preint-bias", choices=["latest", "predicted"], default="latest",
                    help="bias for pre-integrating (k-1,k]: B(k-1)'s estimate after update k-1 (latest) "
                         "or B(k-1)'s initial value (predicted, as src/fusion/window.rs)")
    ap.add_argument("--lag", type=float, default=None, help="smoother lag in seconds (overrides the rule)")
    ap.add_argument("--lag-margin", type=float, default=0.5,
                    help="lag = (window - 1 + margin) / keyframe_hz; margin in keyframe periods, in (0, 1)")
    ap.add_argument("--relinearize-threshold", type=float, default=0.01)
    ap.add_argument("--relinearize-skip", type=int, default=1)
    ap.add_argument("--extra-updates", type=int, default=0,
                    help="empty update() calls after each keyframe (more iSAM2 relinearisation steps)")
    ap.add_argument("--factorization", choices=["cholesky", "qr"], default="cholesky",
                    help="linear solver: iSAM2 CHOLESKY/QR, batch MULTIFRONTAL_CHOLESKY/MULTIFRONTAL_QR. "
                         "QR survives the ill-conditioned no-prior IMU case where Cholesky throws")
    ap.add_argument("--lm-max-iterations", type=int, default=100, help="batch smoother's LM iterations")
    ap.add_argument("--tum-out", help="write the estimated trajectory (TUM: t x y z qx qy qz qw, t + origin)")
    ap.add_argument("--marginals-out", help="write the marginal covariances of the last window's keyframes (JSON)")
    ap.add_argument("--summary-only", action="store_true", help="leave the trajectory out of the JSON")
    ap.add_argument("--compact", action="store_true", help="one-line JSON")
    args = ap.parse_args()

    if args.inputs == "-":
        inputs = json.load(sys.stdin)
    else:
        with open(args.inputs) as f:
            inputs = json.load(f)

    lag, trajectory, smoothed, solve_ms, kept, iterations, failure = run(inputs, args)
    full, trans = ape(inputs, trajectory)
    smoothed_full, smoothed_trans = ape(inputs, smoothed)
    if args.tum_out:
        write_tum(args.tum_out, inputs, trajectory)
    sm = np.asarray(solve_ms) if solve_ms else np.asarray([float("nan")])
    result = {
        "smoother": {"incremental": "IncrementalFixedLagSmoother (iSAM2)",
                     "batch": "BatchFixedLagSmoother (LM)"}[args.smoother],
        "use_imu": bool(inputs.get("use_imu", True)),
        "error_mode": args.error_mode if inputs.get("use_imu", True) else None,
        "preint_bias": args.preint_bias if inputs.get("use_imu", True) else None,
        "window": int(inputs["window"]),
        "keyframe_hz": float(inputs["keyframe_hz"]),
        "lag_seconds": lag,
        # keyframes (X keys) left in the smoother after each update -> number of updates; the solve
        # of each update sees one more (the one it then marginalises), as our window does.
        "keyframes_kept_after_update": {str(n): kept.count(n) for n in sorted(set(kept))},
        "settings": ({"relinearizeThreshold": args.relinearize_threshold,
                      "relinearizeSkip": args.relinearize_skip, "extra_updates": args.extra_updates,
                      "factorization": args.factorization}
                     if args.smoother == "incremental" else
                     {"lm_max_iterations": args.lm_max_iterations, "factorization": args.factorization}),
        "keyframes": len(trajectory),
        # Set when an update threw (statistics then cover the keyframes before it); exit status 2.
        "failed": failure,
        "relative_poses": len(inputs.get("relative_poses", [])),
        "pose_priors": len(inputs.get("pose_priors", [])),
        "ape_full": full,
        "ape_trans": trans,
        # Each keyframe's estimate at the last update it was in the smoother (lag-smoothed).
        "ape_smoothed_full": smoothed_full,
        "ape_smoothed_trans": smoothed_trans,
        "solve_ms": {"p50": float(np.percentile(sm, 50)), "p99": float(np.percentile(sm, 99)),
                     "mean": float(np.mean(sm)), "max": float(np.max(sm))},
        "iterations_mean": float(np.mean(iterations)) if iterations else 0.0,
        "trajectory_tum": args.tum_out,
    }
    if not args.summary_only:
        result["trajectory"] = trajectory
    print(json.dumps(result, separators=(",", ":")) if args.compact else json.dumps(result, indent=2))
    if failure is not None:
        sys.exit(2)


if __name__ == "__main__":
    main()
