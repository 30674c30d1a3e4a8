#!/usr/bin/env python3
"""A BAL problem streamed camera by camera (issue 57 item 5): factord's bundle_adjustment session
over HTTP (a real `factord serve`, journal on, fsync always) against GTSAM iSAM2 on the same
stream, interleaved in one run.

    ~/.cache/factord/venvs/gtsam/bin/python benches/bal/stream.py \\
        [--rounds 3] [--json out.json] [--options '{"max_iterations": 20}'] [problem-49-7776-pre.txt ...]

The stream (the same for both systems): camera c arrives, every point seen by at least two of
cameras 0..c enters when its second camera arrives, with every observation made of it so far,
and each later observation of an entered point arrives with its camera. A BAL problem's points
are all seen twice or more, so the stream ends at the whole problem.

Values: a front-end gives a new camera and its new points in the map it tracks against (PnP,
triangulation), near where the optimum will put them. The BAL files' own initial values are
another thing: a first reconstruction of the whole problem (problem-49's costs 8 × 10⁵, and a
camera streamed with it lands in a map the first cameras have already moved far from). So the
values streamed are the batch optimum (`factord ba --out`) perturbed, with a fixed seed:
rotations by N(0, σ) rad, camera centres and points by N(0, σ · the scene's median radius), σ =
`--noise` (1e-3), focal lengths by the factor 1 + N(0, `--focal-sigma`) (1 %), k1 and k2 as they
are; `--values file` streams the file's own.

Calibration: a robot's front-end knows its camera's focal length (to `--focal-sigma`, 1 %), and
each camera arrives with a prior on it (σ = that fraction of the streamed focal length). Without
it the first cameras' focal lengths and depths trade against each other: on problem-49 both
systems' first sub-problems went to focal lengths 0.6-4.7 × the optimum's, a warped map no later
camera fits (factord ended at 8 × 10⁴ × the optimum, iSAM2 threw). The priors are removed with
the stream's last update, so the idle estimate is the batch problem's (`--focal-sigma 0`: none).

factord: one `POST /v1/sessions/<s>/batches?wait=true` per camera (variables and reprojection
factors, σ = 1 px); latency = request sent → answer read (the answer comes once the solve that
covers the batch has run: the region re-solves of a bundle_adjustment session). After the
stream, `POST …/optimize?wait=true` gives the idle estimate; its cost against the batch optimum
(`factord ba` on the file, the lower of the two).

iSAM2 (GTSAM, `GeneralSFMFactorCal3Bundler`, σ = 1 px, as `gtsam_sfm.py` builds the batch
problem): one `isam.update(new factors, new values)` plus `calculateEstimate()` per camera;
gauge priors on camera 0 (9 parameters) and on the first point to enter (σ `--prior-sigma`);
relinearisation threshold / skip from the options (GTSAM's defaults 0.1 / 10). Once the stream is
done it gets empty updates with forced relinearisation (up to 20, untimed, until its cost
settles to 1e-9), as factord gets its closing optimize. A system that
throws mid-stream (IndeterminantLinearSystemException) is reported with the updates answered.
Its final cost is the BAL cost (½Σ‖r‖², no cheirality test) of its last estimate, against the
BAL reference optimum (MANIFEST.md).

Costs are ½Σ‖r‖² in pixels (factord's chi2 is Σ‖r‖²: halved here). Peak RSS is each system's
process's (the server's VmHWM; the Python process's ru_maxrss for iSAM2).
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import resource
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import C, P

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
from gtsam_sfm import REFERENCE, bal_cost  # noqa: E402

SESSION = "ba_stream"
# Empty iSAM2 updates at most once the stream is done (see run_isam2).
IDLE_UPDATES = 20

# A prior on a BAL camera's focal length: a front-end's calibration (declared as a user factor).
FOCAL_PRIOR = {"name": "focal_length_prior",
               "variables": [{"name": "c", "kind": "snavely_camera"}],
               "parameters": [{"name": "f", "kind": "scalar"}],
               "residual": {"sub": [{"at": [{"intrinsics": ["c"]}, 0]}, "f"]}}


def parse_bal(path):
    """Cameras (n×9), points (m×3) and observations (camera, point, u, v), as the file has them."""
    with open(path) as fh:
        tokens = fh.read().split()
    ncams, npts, nobs = int(tokens[0]), int(tokens[1]), int(tokens[2])
    at = 3
    obs = []
    for _ in range(nobs):
        c, j, u, v = tokens[at:at + 4]
        obs.append((int(c), int(j), float(u), float(v)))
        at += 4
    params = np.array(tokens[at:], dtype=np.float64)
    cameras = params[:9 * ncams].reshape(ncams, 9)
    points = params[9 * ncams:9 * ncams + 3 * npts].reshape(npts, 3)
    return cameras, points, obs


def schedule(cameras, points, obs, min_angle_deg, init_angle_deg):
    """The order an incremental SfM front-end registers cameras in, and when points enter.

    As COLMAP's mapper does (from the geometry of the values streamed): the first two cameras
    are the pair sharing the most points whose rays meet at `min_angle_deg` or more; each next
    camera is the one that sees the most entered points; a point enters, with every observation
    made of it so far, once two registered cameras see it at that angle or more; its later
    observations arrive with their cameras. What never reaches the angle (far points seen along
    the same rays) enters in one last update (camera None, which also removes the focal-length
    priors), so the stream ends at the whole problem. Without
    the angle a two-view point is a depth along nearly parallel rays: iSAM2 throws
    IndeterminantLinearSystem on it, and LM moves it anywhere along them."""
    ncams = len(cameras)
    centres = np.array([-rodrigues(c[:3]).T @ c[3:6] for c in cameras])
    by_camera = [[] for _ in range(ncams)]
    by_point = {}
    for c, j, u, v in obs:
        by_camera[c].append((j, u, v))
        by_point.setdefault(j, []).append(c)
    cos_min = np.cos(np.radians(min_angle_deg))

    def cos_angle(j, a, b):
        ra, rb = centres[a] - points[j], centres[b] - points[j]
        return ra @ rb / (np.linalg.norm(ra) * np.linalg.norm(rb))

    def wide(j, a, b):
        return cos_angle(j, a, b) <= cos_min

    angles = {}
    for j, cams in by_point.items():
        for x in range(len(cams)):
            for y in range(x + 1, len(cams)):
                a, b = min(cams[x], cams[y]), max(cams[x], cams[y])
                angles.setdefault((a, b), []).append(np.degrees(np.arccos(
                    np.clip(cos_angle(j, a, b), -1.0, 1.0))))
    first = pick_first_pair(angles, min_angle_deg, init_angle_deg)
    registered, entered, updates = [], set(), []

    def register(c):
        registered.append(c)
        points_in, observations = [], []
        for j, u, v in by_camera[c]:
            if j in entered:
                observations.append((c, j, u, v))
                continue
            seen = [cc for cc in by_point[j] if cc in registered]
            if any(wide(j, a, b) for a in seen for b in seen if a < b):
                entered.add(j)
                points_in.append(j)
                observations += [(cc, j, uu, vv) for cc in seen
                                 for jj, uu, vv in by_camera[cc] if jj == j]
        updates.append({"camera": c, "points": points_in, "observations": observations})

    register(first[0])
    register(first[1])
    while len(registered) < ncams:
        rest = [c for c in range(ncams) if c not in registered]
        register(max(rest, key=lambda c: sum(j in entered for j, _, _ in by_camera[c])))
    late = set(by_point) - entered
    updates.append({"camera": None, "points": sorted(late), "observations": [
        (c, j, u, v) for c in range(ncams) for j, u, v in by_camera[c] if j in late]})
    return updates


def pick_first_pair(angles, min_angle_deg, init_angle_deg):
    """The pair sharing the most points seen at `min_angle_deg` or more, among the pairs whose
    median such angle is `init_angle_deg` or more (COLMAP's `init_min_tri_angle`, 16°). A
    narrower first pair leaves depth and focal length traded against each other (the bas-relief
    ambiguity): its two-view optimum is a warped map the next cameras cannot be placed in."""
    def wide_count(pair):
        return sum(a >= min_angle_deg for a in angles[pair])

    for limit in (init_angle_deg, init_angle_deg / 2, init_angle_deg / 4, 0.0):
        pairs = [p for p in angles if wide_count(p) >= 20
                 and np.median([a for a in angles[p] if a >= min_angle_deg]) >= limit]
        if pairs:
            return max(pairs, key=wide_count)
    return max(angles, key=wide_count)


def percentile(values, p):
    s = sorted(values)
    pos = (len(s) - 1) * p
    lo, hi = int(pos), min(int(pos) + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


def latency_stats(ms):
    return {"updates": len(ms), "total_s": round(sum(ms) / 1e3, 4),
            "p50_ms": round(percentile(ms, 0.5), 3), "p99_ms": round(percentile(ms, 0.99), 3),
            "worst_ms": round(max(ms), 3)}


def factord_binary():
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/factord/target"))
    binary = os.path.join(target, "release", "factord")
    if not os.access(binary, os.X_OK):
        sys.exit(f"no {binary}: run `cargo build --release`")
    return binary


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def request(conn, method, path, body=None):
    conn.request(method, path, body=None if body is None else json.dumps(body),
                 headers={"content-type": "application/json"})
    response = conn.getresponse()
    data = response.read()
    if response.status >= 300:
        raise RuntimeError(f"{method} {path}: {response.status} {data[:500]!r}")
    return json.loads(data) if data else None


def batch_optimum(path, workdir):
    """`factord ba` on the whole file: its final cost (½Σ‖r‖²)."""
    summary = os.path.join(workdir, "ba.json")
    subprocess.run([factord_binary(), "ba", path, "--summary-json", summary, "--quiet"],
                   check=True, capture_output=True)
    with open(summary) as fh:
        s = json.load(fh)
    return s["final_chi2"] / 2


def write_bal(path, cameras, points, obs):
    with open(path, "w") as fh:
        fh.write(f"{len(cameras)} {len(points)} {len(obs)}\n")
        fh.writelines(f"{c} {j} {float(u)!r} {float(v)!r}\n" for c, j, u, v in obs)
        fh.writelines(f"{float(x)!r}\n" for x in np.concatenate([cameras.ravel(), points.ravel()]))


def streamed_values(path, args, workdir):
    """The file the stream's values come from: the batch optimum perturbed (see above), or the
    file itself."""
    if args.values == "file":
        return path
    optimum = os.path.join(workdir, "optimum.bal")
    subprocess.run([factord_binary(), "ba", path, "--out", optimum, "--quiet"], check=True,
                   capture_output=True)
    cameras, points, obs = parse_bal(optimum)
    rng = np.random.default_rng(args.seed)
    radius = float(np.median(np.linalg.norm(points - np.median(points, axis=0), axis=1)))
    cameras, points = cameras.copy(), points.copy()
    rotations = cameras[:, :3].copy()
    centres = [-rodrigues(r).T @ t for r, t in zip(rotations, cameras[:, 3:6])]
    cameras[:, :3] += rng.normal(0.0, args.noise, rotations.shape)
    for i, centre in enumerate(centres):
        moved = centre + rng.normal(0.0, args.noise * radius, 3)
        cameras[i, 3:6] = -rodrigues(cameras[i, :3]) @ moved
    points += rng.normal(0.0, args.noise * radius, points.shape)
    cameras[:, 6] *= 1.0 + rng.normal(0.0, args.focal_sigma, len(cameras))
    perturbed = os.path.join(workdir, "streamed.bal")
    write_bal(perturbed, cameras, points, obs)
    return perturbed


def rodrigues(w):
    theta = float(np.linalg.norm(w))
    if theta < 1e-15:
        return np.eye(3)
    k = w / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def run_factord(bal, updates, args):
    cameras, points, _ = bal
    workdir = tempfile.mkdtemp(prefix="ba-stream-")
    port = free_port()
    server = subprocess.Popen(
        [factord_binary(), "serve", "--listen", f"127.0.0.1:{port}", "--state-dir",
         os.path.join(workdir, "state"), "--no-zenoh", "--fsync", args.fsync],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                conn = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
                request(conn, "GET", "/v1/health")
                break
            except (ConnectionRefusedError, OSError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        create = {"session": SESSION, "kind": "bundle_adjustment", "factor_types": [FOCAL_PRIOR]}
        if args.options:
            create["options"] = json.loads(args.options)
        request(conn, "POST", "/v1/sessions", create)
        ncams = len(cameras)
        ms, unsolved, priors = [], 0, []
        for update in updates:
            c = update["camera"]
            variables = [] if c is None else [
                {"key": c, "kind": "snavely_camera", "value": cameras[c].tolist()}]
            variables += [{"key": ncams + j, "kind": "point3", "value": points[j].tolist()}
                          for j in update["points"]]
            factors = [{"type": "reprojection_snavely", "keys": [c, ncams + j],
                        "measurement": [u, v], "sigmas": [1.0, 1.0]}
                       for c, j, u, v in update["observations"]]
            batch = {"variables": variables, "factors": factors}
            if c is None:
                batch["remove_factors"] = priors
            elif args.focal_sigma > 0:
                f = float(cameras[c, 6])
                factors.append({"type": FOCAL_PRIOR["name"], "keys": [c], "measurement": [f],
                                "sigmas": [args.focal_sigma * f]})
            body = json.dumps(batch)
            t = time.perf_counter()
            conn.request("POST", f"/v1/sessions/{SESSION}/batches?wait=true", body=body,
                         headers={"content-type": "application/json"})
            response = conn.getresponse()
            answer = response.read()
            ms.append((time.perf_counter() - t) * 1e3)
            if response.status != 200:
                raise RuntimeError(f"batch {c}: {response.status} {answer[:300]!r}")
            answer = json.loads(answer)
            unsolved += not answer.get("solved", False)
            if c is not None and args.focal_sigma > 0:
                priors.append(answer["factor_ids"][-1])
        streamed = request(conn, "GET", f"/v1/sessions/{SESSION}")
        t = time.perf_counter()
        optimized = request(conn, "POST", f"/v1/sessions/{SESSION}/optimize?wait=true", {})
        idle_s = time.perf_counter() - t
        with open(f"/proc/{server.pid}/status") as fh:
            hwm = next(int(l.split()[1]) for l in fh if l.startswith("VmHWM"))
        final = optimized["stats"]["chi2"] / 2
        optimum = min(batch_optimum(args.path, workdir), final)
        return {"system": "factord HTTP", **latency_stats(ms), "unsolved_answers": unsolved,
                "streamed_cost": streamed.get("chi2", float("nan")) / 2,
                "idle_optimize_s": round(idle_s, 3), "final_cost": final,
                "batch_optimum": optimum, "gap": final / optimum - 1,
                "peak_rss_mb": round(hwm / 1024, 1), "latencies_ms": ms}
    finally:
        server.terminate()
        server.wait()
        shutil.rmtree(workdir, ignore_errors=True)


def run_isam2(updates, args):
    data = gtsam.SfmData.FromBalFile(args.values_path)
    measured = {}
    for j in range(data.numberTracks()):
        track = data.track(j)
        for k in range(track.numberMeasurements()):
            i, uv = track.measurement(k)
            measured[(i, j)] = uv
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(args.relinearize_threshold)
    params.relinearizeSkip = args.relinearize_skip
    if args.dogleg:
        params.setOptimizationParams(gtsam.ISAM2DoglegParams())
    isam = gtsam.ISAM2(params)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    prior9 = gtsam.noiseModel.Isotropic.Sigma(9, args.prior_sigma)
    prior3 = gtsam.noiseModel.Isotropic.Sigma(3, args.prior_sigma)
    # The focal-length prior: a camera prior weighing only f (a pose or k σ of 1e4 weighs
    # nothing against 1-pixel reprojections).
    focal = lambda f: gtsam.noiseModel.Diagonal.Sigmas(
        np.array([1e4] * 6 + [args.focal_sigma * f, 1e4, 1e4]))
    ms, failure, point_prior, priors = [], None, False, []
    estimate = None
    for update in updates:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        c = update["camera"]
        removed = priors if c is None else []
        if c is not None:
            values.insert(C(c), data.camera(c))
            if args.focal_sigma > 0:
                graph.add(gtsam.PriorFactorPinholeCameraCal3Bundler(
                    C(c), data.camera(c), focal(data.camera(c).calibration().fx())))
        if not ms and failure is None and c is not None and not update["points"]:
            # The first camera: the gauge prior (as gtsam_sfm.py, on the first one registered).
            graph.add(gtsam.PriorFactorPinholeCameraCal3Bundler(C(c), data.camera(c), prior9))
        for j in update["points"]:
            values.insert(P(j), data.track(j).point3())
            if not point_prior:
                graph.add(gtsam.PriorFactorPoint3(P(j), data.track(j).point3(), prior3))
                point_prior = True
        for cc, j, _, _ in update["observations"]:
            graph.add(gtsam.GeneralSFMFactorCal3Bundler(measured[(cc, j)], noise, C(cc), P(j)))
        t = time.perf_counter()
        try:
            result = isam.update(graph, values, removed)
            if c is not None and args.focal_sigma > 0:
                priors.append(result.getNewFactorsIndices()[0])
            estimate = isam.calculateEstimate()
        except RuntimeError as e:
            failure = {"camera": c, "error": f"{type(e).__name__}: {e}"[:300]}
            break
        ms.append((time.perf_counter() - t) * 1e3)
    idle_s, idle_updates = 0.0, 0
    if failure is None:
        # Idle, as factord's closing optimize: iSAM2 takes one Gauss-Newton step per update, so
        # it gets empty updates (relinearising everything that moved) until its cost settles.
        t = time.perf_counter()
        cost = bal_cost(data, estimate)[0]
        for idle_updates in range(1, IDLE_UPDATES + 1):
            isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], None, None, None, True)
            estimate = isam.calculateEstimate()
            settled, cost = cost, bal_cost(data, estimate)[0]
            if abs(settled - cost) <= 1e-9 * cost:
                break
        idle_s = time.perf_counter() - t
    result = {"system": "iSAM2", **latency_stats(ms), "failure": failure,
              "relinearize": [args.relinearize_threshold, args.relinearize_skip],
              "idle_updates": idle_updates, "idle_s": round(idle_s, 3),
              "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
              "latencies_ms": ms}
    if failure is None:
        final, behind = bal_cost(data, estimate)
        reference = REFERENCE.get(os.path.basename(args.path))
        result.update({"final_cost": final, "behind_camera": behind, "reference": reference,
                       "gap": None if reference is None else final / reference - 1})
    return result


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("problems", nargs="*", default=["problem-49-7776-pre.txt"])
    p.add_argument("--data", default=os.path.join(REPO, "..", "shared", "data", "bal"))
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--fsync", default="always")
    p.add_argument("--prior-sigma", type=float, default=0.1)
    p.add_argument("--relinearize-threshold", type=float, default=0.1)
    p.add_argument("--relinearize-skip", type=int, default=10)
    p.add_argument("--systems", default="factord,isam2")
    p.add_argument("--min-angle", type=float, default=2.0,
                   help="a point enters once two registered cameras see it at this angle (deg)")
    p.add_argument("--init-angle", type=float, default=16.0,
                   help="the first pair's median triangulation angle, at least (deg)")
    p.add_argument("--dogleg", action="store_true", help="iSAM2 with Powell's dogleg steps")
    p.add_argument("--values", choices=("optimum", "file"), default="optimum")
    p.add_argument("--noise", type=float, default=1e-3)
    p.add_argument("--focal-sigma", type=float, default=0.01,
                   help="focal lengths perturbed and each camera's prior, as a fraction of f")
    p.add_argument("--seed", type=int, default=57)
    p.add_argument("--json", help="every round's reports, latencies included")
    p.add_argument("--options", help="factord's session solver options (JSON), e.g. "
                   "'{\"max_iterations\": 20}'")
    args = p.parse_args()
    reports = []
    for name in args.problems:
        args.path = name if os.path.exists(name) else os.path.join(args.data, name)
        values_dir = tempfile.mkdtemp(prefix="ba-stream-values-")
        args.values_path = streamed_values(args.path, args, values_dir)
        bal = parse_bal(args.values_path)
        # iSAM2 reads the values file itself (SfmData converts BAL's conventions).
        updates = schedule(*bal, args.min_angle, args.init_angle)
        rounds = {"factord": [], "isam2": []}
        for _ in range(args.rounds):
            for system in args.systems.split(","):
                report = run_factord(bal, updates, args) if system == "factord" \
                    else run_isam2(updates, args)
                report["problem"] = name
                rounds[system].append(report)
                reports.append(report)
                shown = {k: v for k, v in report.items() if k != "latencies_ms"}
                print(json.dumps(shown), file=sys.stderr, flush=True)
        table(name, len(updates), rounds)
        shutil.rmtree(values_dir, ignore_errors=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(reports, fh)


def table(name, updates, rounds):
    """The medians over rounds, and factord / iSAM2."""
    keys = ("total_s", "p50_ms", "p99_ms", "worst_ms", "peak_rss_mb")
    med = {s: {k: statistics.median(r[k] for r in rs) for k in keys} for s, rs in rounds.items() if rs}
    print(f"\n{name}: {updates} cameras streamed (median of {max(len(r) for r in rounds.values())})")
    print("| | " + " | ".join(keys) + " | final cost gap |")
    print("|---" * (len(keys) + 2) + "|")
    for s, rs in rounds.items():
        if rs:
            gaps = [r.get("gap") for r in rs]
            print(f"| {rs[0]['system']} | " + " | ".join(f"{med[s][k]:g}" for k in keys)
                  + f" | {gaps} |")
    if len(med) == 2:
        print("| factord / iSAM2 | " + " | ".join(
            f"{med['factord'][k] / med['isam2'][k]:.3f}" for k in keys) + " | |")


if __name__ == "__main__":
    main()
