#!/usr/bin/env python3
"""factord ba against Ceres (DENSE_SCHUR, SPARSE_SCHUR; one thread) on BAL problems, interleaved.

    compare.py [--rounds 3] [--huber SCALE] [--data DIR] [problem ...]

Builds nothing: run `cargo build --release` and `benches/reference/ceres/build.sh` first.
Defaults to the two acceptance problems. Prints a markdown table of median solve times (the
Solve call / the optimisation, file parsing excluded) and final costs (½Σ‖r‖²).
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


def main():
    p = argparse.ArgumentParser()
    p.add_argument("problems", nargs="*")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--huber", type=float, default=0.0)
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
    rows = []
    for problem in problems:
        runs = {"factord": [], "ceres dense_schur": [], "ceres sparse_schur": []}
        for _ in range(args.rounds):
            with tempfile.NamedTemporaryFile(suffix=".json") as f:
                cmd = [factord, "ba", problem, "--quiet", "--summary-json", f.name]
                if args.huber:
                    cmd += ["--robust", f"huber:{args.huber}"]
                subprocess.run(cmd, check=True)
                s = json.load(open(f.name))
                runs["factord"].append((s["solve_seconds"], s["final_cost"], s["iterations"], s["converged"]))
            for solver in ("dense_schur", "sparse_schur"):
                cmd = [ceres, problem, "--linear-solver", solver]
                if args.huber:
                    cmd += ["--huber", str(args.huber)]
                out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
                c = json.loads(out)
                runs[f"ceres {solver}"].append((c["solve_seconds"], c["final_cost"], c["iterations"], c["converged"]))
        best = min(statistics.median(r[0] for r in v) for k, v in runs.items() if k != "factord")
        for system, v in runs.items():
            t = statistics.median(r[0] for r in v)
            rows.append(f"| {os.path.basename(problem)} | {system} | {t:.3f} | {v[-1][1]:.4f} | "
                        f"{v[-1][2]} | {v[-1][3]} | {t / best:.2f} |")
    print(f"{args.rounds} interleaved rounds, median solve seconds" + (f", Huber({args.huber})" if args.huber else ""))
    print()
    print("| problem | system | solve s | final cost | iterations | converged | / fastest Ceres |")
    print("|---|---|---:|---:|---:|---|---:|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
