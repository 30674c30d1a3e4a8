#!/usr/bin/env python3
"""factord ba against Ceres (DENSE_SCHUR, SPARSE_SCHUR) on BAL problems, interleaved.

    compare.py [--rounds 3] [--huber SCALE] [--threads 1[,2]] [--solvers dense_schur,sparse_schur]
               [--max-iterations N] [--data DIR] [problem ...]

Builds nothing: run `cargo build --release` and `benches/reference/ceres/build.sh` first.
Defaults to the two acceptance problems, one thread. Every system runs once per thread count
given (factord `--threads N`, Ceres `num_threads`). Prints a markdown table of median solve times
(the Solve call / the optimisation, file parsing excluded), final costs (½Σ‖r‖²), peak RSS of the
process (GNU time's %M, the whole process: parsing included) and each time over the fastest
single-thread Ceres of the same problem in the same run. factord's row names the reduced
system its `auto` choice took (explicit, or implicit with its CG iterations). `--max-iterations`
stops both after N LM iterations: for problems whose whole solve takes Ceres minutes
(`synthetic.py 1000 300000`), compared at that point.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))


def timed(cmd):
    """Runs `cmd` under GNU time; returns its standard output and peak RSS in KB."""
    with tempfile.NamedTemporaryFile(suffix=".txt") as t:
        out = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", t.name] + cmd, check=True,
                             capture_output=True, text=True).stdout
        return out, int(open(t.name).read().split()[-1])


def main():
    p = argparse.ArgumentParser()
    p.add_argument("problems", nargs="*")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--huber", type=float, default=0.0)
    p.add_argument("--threads", default="1", help="comma-separated thread counts, e.g. 1,2")
    p.add_argument("--solvers", default="dense_schur,sparse_schur", help="Ceres linear solvers")
    p.add_argument("--max-iterations", type=int, default=0, help="stop both after N iterations")
    p.add_argument("--data", default=os.path.join(REPO, "..", "shared", "data"))
    args = p.parse_args()
    problems = args.problems or [os.path.join(args.data, "bal", f)
                                 for f in ("problem-16-22106-pre.txt", "problem-49-7776-pre.txt")]
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/factord/target"))
    factord = os.path.join(target, "release", "factord")
    ceres = os.path.join(os.environ.get("FACTORD_BENCH_BIN", os.path.expanduser("~/.cache/factord/bin")), "ceres_bal")
    for exe in (factord, ceres):
        if not os.access(exe, os.X_OK):
            sys.exit(f"missing {exe}")
    threads = [int(t) for t in args.threads.split(",")]
    solvers = args.solvers.split(",")
    rows = []
    for problem in problems:
        runs = {}
        for _ in range(args.rounds):
            for t in threads:
                with tempfile.NamedTemporaryFile(suffix=".json") as f:
                    cmd = [factord, "ba", problem, "--quiet", "--threads", str(t), "--summary-json", f.name]
                    if args.huber:
                        cmd += ["--robust", f"huber:{args.huber}"]
                    if args.max_iterations:
                        cmd += ["--max-iterations", str(args.max_iterations)]
                    rss = timed(cmd)[1]
                    s = json.load(open(f.name))
                    schur = (s.get("used") or {}).get("schur") or {}
                    name = "factord " + schur.get("reduced_factorization", "")
                    if schur.get("reduced_factorization") == "implicit":
                        name += f" ({schur['cg_iterations']} CG)"
                    runs.setdefault((name.strip(), t), []).append(
                        (s["solve_seconds"], s["final_cost"], s["iterations"], s["converged"], rss))
                for solver in solvers:
                    cmd = [ceres, problem, "--linear-solver", solver, "--threads", str(t)]
                    if args.huber:
                        cmd += ["--huber", str(args.huber)]
                    if args.max_iterations:
                        cmd += ["--max-iterations", str(args.max_iterations)]
                    out, rss = timed(cmd)
                    c = json.loads(out)
                    runs.setdefault((f"ceres {solver}", t), []).append(
                        (c["solve_seconds"], c["final_cost"], c["iterations"], c["converged"], rss))
        best = min(statistics.median(r[0] for r in v) for (k, t), v in runs.items()
                   if k.startswith("ceres") and t == 1)
        for (system, t), v in runs.items():
            time = statistics.median(r[0] for r in v)
            rss = max(r[4] for r in v)
            rows.append(f"| {os.path.basename(problem)} | {system} | {t} | {time:.3f} | {v[-1][1]:.4f} | "
                        f"{v[-1][2]} | {v[-1][3]} | {rss / 1024:.0f} | {time / best:.2f} |")
    print(f"{args.rounds} interleaved rounds, median solve seconds" + (f", Huber({args.huber})" if args.huber else ""))
    print()
    print("| problem | system | threads | solve s | final cost | iterations | converged | peak RSS MB | / fastest 1-thread Ceres |")
    print("|---|---|---:|---:|---:|---:|---|---:|---:|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
