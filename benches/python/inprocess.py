#!/usr/bin/env python3
"""GTSAM and factord in process, in the same Python process and run (issue 56, item 2).

Both libraries are imported side by side: run this with the python of a venv that has GTSAM
(`~/.cache/factord/venvs/gtsam`, made by the test command) and put the factord wheel on
PYTHONPATH (built by `maturin build --release` from clients/python/native, installed with
`pip install --target <dir>`); `--build` does both. Cases, interleaved per round, medians over
rounds:

- batch LM on input_M3500_g2o and sphere2500 through readG2o, from the files' initial guesses,
  the same params for both (relative error tolerance 1e-6, at most 100 iterations), a prior on
  the first pose; timed from the optimizer's construction to the end of optimize();
- an ISAM2 stream of M3500: update k adds pose k (guessed from the previous estimate and the
  odometry) and every edge whose later end is k; relinearizeThreshold 0.1, relinearizeSkip 1 for
  GTSAM; per-update times, total, and the final error over the batch optimum;
- bundle adjustment of problem-49-7776 (BAL): GTSAM's SFMExample_bal.py way against factord's
  loadBal, LM from the file's start (each error in its own measure: GTSAM's includes its gauge
  priors);
- factord's own `solve()` (library defaults: GN, chordal start when it helps), warm, on intel and
  sphere2500 against `factord solve --summary-json` (the CLI's median solve_seconds): the cost of
  calling in process; each side in `--processes` processes (fresh Python processes for factord),
  alternating, pooled medians.

Each library reports its error in its own measure: the 2D between errors differ by definition
(GTSAM: Logmap; factord: g2o's), and GTSAM's readG2o and factord weigh a 3D file's rotation
information differently (factord maps g2o's quaternion-vector error onto the angle, D Ω D).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(REPO, "benches", "bal"))


def build_factord(target_dir, scratch):
    """Builds the wheel and installs it into scratch/site; returns that directory."""
    wheels, site = os.path.join(scratch, "wheels"), os.path.join(scratch, "site")
    env = dict(os.environ, CARGO_TARGET_DIR=target_dir)
    maturin = [sys.executable, "-m", "maturin"]
    if subprocess.run(maturin + ["--version"], capture_output=True).returncode != 0:
        maturin = [os.path.expanduser("~/.cache/factord/venvs/native/bin/python"), "-m", "maturin"]
    subprocess.run(maturin + ["build", "--release", "--locked", "--quiet", "--manifest-path",
                              os.path.join(REPO, "clients/python/native/Cargo.toml"),
                              "--interpreter", sys.executable, "--out", wheels], check=True, env=env)
    wheel = [w for w in os.listdir(wheels) if w.endswith(".whl")][0]
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", site,
                    os.path.join(wheels, wheel)], check=True)
    return site


def batch(lib, path, is3d):
    graph, initial = lib.readG2o(path, is3d)
    if is3d:
        first = initial.atPose3(0)
        graph.add(lib.PriorFactorPose3(0, first, lib.noiseModel.Isotropic.Sigma(6, 1e-4)))
    else:
        first = initial.atPose2(0)
        graph.add(lib.PriorFactorPose2(0, first, lib.noiseModel.Isotropic.Sigma(3, 1e-4)))
    params = lib.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-6)
    params.setMaxIterations(100)
    start = time.perf_counter()
    optimizer = lib.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "error": graph.error(result), "iterations": optimizer.iterations()}


def isam2_stream(lib, path, gtsam_like):
    graph, initial = lib.readG2o(path, False)
    by_step = {}
    for i in range(graph.size()):
        f = graph.at(i)
        a, b = f.keys()
        by_step.setdefault(max(a, b), []).append(f)
    params = lib.ISAM2Params()
    params.setRelinearizeThreshold(0.1)
    if gtsam_like:
        params.relinearizeSkip = 1
    isam = lib.ISAM2(params)
    estimate = None
    times = []
    keys = sorted(initial.keys())
    start = time.perf_counter()
    for k in keys:
        new_graph, new_values = lib.NonlinearFactorGraph(), lib.Values()
        if estimate is None:
            guess = initial.atPose2(k)
            new_graph.add(lib.PriorFactorPose2(k, guess, lib.noiseModel.Isotropic.Sigma(3, 1e-4)))
        else:
            odometry = [f for f in by_step.get(k, []) if k - 1 in f.keys()]
            guess = estimate.atPose2(k - 1).compose(odometry[0].measured()) if odometry else initial.atPose2(k)
        new_values.insert(k, guess)
        for f in by_step.get(k, []):
            new_graph.add(f)
        t = time.perf_counter()
        isam.update(new_graph, new_values)
        estimate = isam.calculateEstimate()
        times.append(time.perf_counter() - t)
    total = time.perf_counter() - start
    whole = isam.getFactorsUnsafe()
    times.sort()
    return {
        "total": total,
        "p50_ms": 1e3 * times[len(times) // 2],
        "p99_ms": 1e3 * times[int(0.99 * (len(times) - 1))],
        "worst_ms": 1e3 * times[-1],
        "error": whole.error(estimate),
        "graph": whole,
        "estimate": estimate,
    }


def bundle_adjustment(lib, path, is_gtsam):
    """LM on a BAL file, at most 50 iterations, relative error tolerance 1e-6. GTSAM as its
    SFMExample_bal.py builds it (benches/bal/gtsam_sfm.py: GeneralSFMFactorCal3Bundler with unit
    noise, priors σ 0.1 on the first camera and point for the gauge); factord through loadBal
    (the points eliminated by the Schur complement, the gauge left to the damping)."""
    if is_gtsam:
        graph, priors, initial = gtsam_sfm.build(lib.SfmData.FromBalFile(path), 0.1)
        graph.push_back(priors)
    else:
        graph, initial = lib.loadBal(path)
    params = lib.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    params.setRelativeErrorTol(1e-6)
    start = time.perf_counter()
    optimizer = lib.LevenbergMarquardtOptimizer(graph, initial, params)
    optimizer.optimize()
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "error": optimizer.error(), "iterations": optimizer.iterations()}


INPROCESS_SOLVE = """
import json, sys, time
import factord
path, repeat = sys.argv[1], int(sys.argv[2])
graph, initial = factord.readG2o(path, "3d" in path)
factord.solve(graph, initial, method="gauss_newton", initialization="auto")
runs = []
for _ in range(repeat):
    start = time.perf_counter()
    _, summary = factord.solve(graph, initial, method="gauss_newton", initialization="auto")
    runs.append({"seconds": time.perf_counter() - start, "solve_seconds": summary["solve_seconds"],
                 "chi2": summary["final_chi2"]})
print(json.dumps(runs))
"""


def inprocess_solve(site, path, repeat):
    """`repeat` warm calls of factord.solve() in a fresh Python process (factord from `site`)."""
    env = dict(os.environ, PYTHONPATH=site + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", INPROCESS_SOLVE, path, str(repeat)], env=env,
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out)


def cli_solve(factord_bin, path, repeat):
    out = subprocess.run([factord_bin, "solve", path, "--summary-json", "-", "--repeat", str(repeat), "--quiet"],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out[out.index("{"):])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("FACTORD_BENCH_DATA", os.path.join(REPO, "../shared/data")))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--build", action="store_true", help="build and install the factord wheel first")
    ap.add_argument("--target-dir", default=os.environ.get("CARGO_TARGET_DIR", os.path.join(REPO, "target")))
    ap.add_argument("--factord-bin", help="factord binary for the CLI comparison (default: <target-dir>/release/factord)")
    ap.add_argument("--skip-stream", action="store_true")
    ap.add_argument("--processes", type=int, default=3,
                    help="processes per side of the in-process-against-CLI comparison")
    args = ap.parse_args()
    if args.build:
        sys.path.insert(0, build_factord(args.target_dir, tempfile.mkdtemp(prefix="factord-bench-")))
    import gtsam
    import factord
    global gtsam_sfm
    import gtsam_sfm  # benches/bal: GTSAM's BAL graph as SFMExample_bal.py builds it

    m3500 = os.path.join(args.data, "2d/carlone/input_M3500_g2o.g2o")
    sphere = os.path.join(args.data, "3d/sesync/sphere2500.g2o")
    intel = os.path.join(args.data, "2d/carlone/input_INTEL_g2o.g2o")
    bal49 = os.path.join(args.data, "bal/problem-49-7776-pre.txt")
    results = {}

    def record(case, system, value):
        results.setdefault(case, {}).setdefault(system, []).append(value)

    for r in range(args.rounds):
        for name, path, is3d in (("M3500 batch LM", m3500, False), ("sphere2500 batch LM", sphere, True)):
            for system, lib in (("gtsam", gtsam), ("factord", factord)):
                record(name, system, batch(lib, path, is3d))
        if os.path.exists(bal49):
            for system, lib in (("gtsam", gtsam), ("factord", factord)):
                record("problem-49 BA LM", system, bundle_adjustment(lib, bal49, system == "gtsam"))
        if not args.skip_stream and r < 2:
            for system, lib in (("gtsam", gtsam), ("factord", factord)):
                s = isam2_stream(lib, m3500, system == "gtsam")
                record("M3500 ISAM2 stream", system, {k: v for k, v in s.items() if k not in ("graph", "estimate")})
    # solve() against the CLI, both warm: the CLI's --repeat N median in one process against N
    # calls in a row in a fresh Python process after one untimed call (the first solve in a
    # process pays for first touches of memory: sphere2500's took 3x the others in a trial).
    # A process's own speed moves by about 15 % here at a few milliseconds, so each side runs
    # in `--processes` processes, alternating, and the ratio is of the pooled medians.
    factord_bin = args.factord_bin or os.path.join(args.target_dir, "release/factord")
    repeat = max(args.rounds, 15)
    site = os.path.dirname(os.path.dirname(factord.__file__))
    for name, path in (("intel solve()", intel), ("sphere2500 solve()", sphere)):
        for _ in range(args.processes):
            if os.path.exists(factord_bin):
                s = cli_solve(factord_bin, path, repeat)
                record(name, "factord solve", {"seconds": s["solve_seconds"], "chi2": s["final_chi2"]})
            for run in inprocess_solve(site, path, repeat):
                record(name, "in process", run)

    print(f"# {args.rounds} rounds, medians")
    for case, systems in results.items():
        line = [f"{case}:"]
        med = {}
        for system, runs in systems.items():
            key = "total" if "stream" in case else "seconds"
            med[system] = statistics.median(run[key] for run in runs)
            extra = ""
            last = runs[-1]
            if "error" in last:
                extra = f", error {last['error']:.6f}"
            if "p50_ms" in last:
                extra += f", p50 {statistics.median(x['p50_ms'] for x in runs):.2f} ms, p99 {statistics.median(x['p99_ms'] for x in runs):.2f} ms, worst {statistics.median(x['worst_ms'] for x in runs):.2f} ms"
            if "iterations" in last:
                extra += f", {last['iterations']} iterations"
            if "solve_seconds" in last:
                extra += f" (the library's solve_seconds {1e3 * statistics.median(x['solve_seconds'] for x in runs):.1f} ms)"
            if "chi2" in last:
                extra += f", chi2 {last['chi2']:.6f}"
            line.append(f"  {system}: {med[system] * 1e3:.1f} ms{extra}")
        names = list(med)
        if "factord solve" in med:
            names = ["factord solve", "in process"]
        if len(names) == 2:
            line.append(f"  ratio {names[1]} / {names[0]}: {med[names[1]] / med[names[0]]:.3f}")
        print("\n".join(line))


if __name__ == "__main__":
    main()
