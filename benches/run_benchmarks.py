#!/usr/bin/env python3
"""Benchmark factord against g2o, GTSAM and Ceres on the standard pose-graph datasets.

    python3 benches/run_benchmarks.py [--factord BIN] [--ceres BIN] [--data DIR] [--repeat 5]
                                      [--only intel,sphere2500] [--systems factord,g2o-gn,...]
                                      [--markdown OUT.md] [--json OUT.json] [--timeout 1800]

Standard library only.  The reference drivers run in their own venvs (create them with
benches/reference/setup.sh):  $FACTORD_BENCH_VENVS/{gtsam,g2o}/bin/python
(default FACTORD_BENCH_VENVS = ~/.cache/factord/venvs).  The Ceres driver is built by
benches/reference/ceres/build.sh (default ${FACTORD_BENCH_BIN:-~/.cache/factord/bin}/ceres_pose_graph).

What is timed (all times are medians over --repeat runs from the file's initial guess):
  factord  `factord solve FILE [--edges E] --summary-json T --quiet --repeat N [--factord-args ...]`:
           N solves in one process from the same initial values; each run's `solve_seconds` (optimisation
           only: preprocessing, initialisation and iterations, not file loading).
  g2o      benches/reference/g2o_solve.py: optimize() (initialize_optimization() is reported
           separately, not included); stop on relative chi2 gain < 1e-6.
  gtsam    benches/reference/gtsam_solve.py: optimizer construction + optimize(); relTol 1e-6.
           3D runs use --se3-info g2o (rotation information scaled so GTSAM minimises the same
           cost as g2o and factord up to O(theta^3)); otherwise the optima are not comparable.
  ceres    the Ceres driver's own timing (see its source).
A system that is missing (binary / venv absent) is skipped with a message.

Optimum agreement: factord's chi2 in g2o's convention (2D: `final_chi2`, t2v error;
3D: `final_chi2_g2o`, [t; qvec] error) is compared with every converged reference's
`final_chi2_g2o`.  Relative tolerance 1e-6 in 2D and 1e-3 (0.1 %) in 3D.  References that errored
or did not converge are shown as such and excluded from the agreement check and from
"fastest ref".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

REPO = Path(__file__).resolve().parents[1]
REFERENCE_DIR = REPO / "benches" / "reference"
DEFAULT_DATA = Path(os.environ.get("FACTORD_BENCH_DATA", "/work/shared/data"))
VENVS = Path(os.environ.get("FACTORD_BENCH_VENVS", Path.home() / ".cache" / "factord" / "venvs"))
BIN_DIR = Path(os.environ.get("FACTORD_BENCH_BIN", Path.home() / ".cache" / "factord" / "bin"))
# In the build directory of .ci/run and benches/run.sh, as every other bench script looks for it.
TARGET = os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache" / "factord" / "target")
DEFAULT_FACTORD = Path(TARGET) / "release" / "factord"
DEFAULT_CERES = BIN_DIR / "ceres_pose_graph"

TOLERANCE = {2: 1e-6, 3: 1e-3}


@dataclass(frozen=True)
class Dataset:
    name: str
    dim: int
    factord_file: str                   # relative to the data dir
    factord_edges: Optional[str]        # separate edge file for factord, if any
    reference_file: str                 # single g2o file given to the reference drivers


DATASETS = [
    Dataset("intel", 2, "2d/ls_slam/intel-v.dat", "2d/ls_slam/intel-e.dat", "2d/converted/intel_lsslam.g2o"),
    Dataset("killian", 2, "2d/ls_slam/killian-v.dat", "2d/ls_slam/killian-e.dat", "2d/converted/killian_lsslam.g2o"),
    Dataset("input_INTEL_g2o", 2, "2d/carlone/input_INTEL_g2o.g2o", None, "2d/carlone/input_INTEL_g2o.g2o"),
    Dataset("input_M3500_g2o", 2, "2d/carlone/input_M3500_g2o.g2o", None, "2d/carlone/input_M3500_g2o.g2o"),
    Dataset("manhattanOlson3500", 2, "2d/misc/manhattanOlson3500.g2o", None, "2d/misc/manhattanOlson3500.g2o"),
    Dataset("sphere2500", 3, "3d/sesync/sphere2500.g2o", None, "3d/sesync/sphere2500.g2o"),
    Dataset("torus3D", 3, "3d/sesync/torus3D.g2o", None, "3d/sesync/torus3D.g2o"),
]

# column key -> header
SYSTEMS = {
    "factord": "factord",
    "g2o-gn": "g2o GN",
    "g2o-lm": "g2o LM",
    "gtsam-gn": "gtsam GN",
    "gtsam-lm": "gtsam LM",
    "ceres": "ceres",
}
REFERENCES = [k for k in SYSTEMS if k != "factord"]


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def error_result(system: str, message: str) -> Dict[str, Any]:
    return {"system": system, "error": message, "converged": False, "solve_seconds": None}


def run_json(cmd: List[str], system: str, timeout: float) -> Dict[str, Any]:
    """Run a driver that prints one JSON object on stdout (last non-empty line)."""
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return error_result(system, f"timeout after {timeout:.0f} s")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    try:
        result = json.loads(lines[-1])
    except (IndexError, json.JSONDecodeError):
        tail = (proc.stderr.strip().splitlines() or [""])[-1]
        return error_result(system, f"exit code {proc.returncode}, no JSON output; {tail}".strip())
    if proc.returncode != 0 and not result.get("error"):
        result["error"] = f"exit code {proc.returncode}"
    return result


# ---------------------------------------------------------------------------------------------
# systems
# ---------------------------------------------------------------------------------------------

def run_factord(binary: Path, ds: Dataset, data: Path, repeat: int, extra: List[str],
                timeout: float) -> Dict[str, Any]:
    cmd = [str(binary), "solve", str(data / ds.factord_file)]
    if ds.factord_edges:
        cmd += ["--edges", str(data / ds.factord_edges)]
    runs, summary = [], None
    with tempfile.TemporaryDirectory(prefix="factord-bench-") as tmp:
        out = Path(tmp) / "summary.json"
        # One process, --repeat solves from the same initial values (as the reference drivers
        # repeat inside one Python process).
        full = cmd + ["--summary-json", str(out), "--quiet", "--repeat", str(repeat)] + extra
        try:
            proc = subprocess.run(full, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return error_result("factord", f"timeout after {timeout:.0f} s")
        if proc.returncode != 0 or not out.exists():
            msg = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
            return error_result("factord", msg)
        summary = json.loads(out.read_text())
        runs = summary.get("solve_seconds_runs") or [summary["solve_seconds"]]
    termination = summary.get("termination") or {}
    converged = summary.get("converged")
    if converged is None:
        converged = termination.get("reason") not in ("max_iterations", "no_progress")
    final = summary.get("final_chi2")
    final_g2o = summary.get("final_chi2_g2o", final if ds.dim == 2 else None)
    return {
        "system": "factord",
        "method": summary.get("method"),
        "command": " ".join(shlex.quote(c) for c in full),
        "dim": ds.dim,
        "initial_chi2": summary.get("initial_chi2"),
        "final_chi2": final,
        "final_chi2_g2o": final_g2o,
        "iterations": summary.get("iterations"),
        "termination": termination.get("reason"),
        "termination_message": termination.get("message"),
        "solve_seconds_runs": runs,
        "solve_seconds": statistics.median(runs),
        "converged": bool(converged),
        "error": None,
    }


def reference_command(key: str, ds: Dataset, data: Path, repeat: int, ceres: Path) -> Optional[List[str]]:
    """Command for a reference system, or None with a log message if it is unavailable."""
    path = str(data / ds.reference_file)
    if key == "ceres":
        if not (ceres.is_file() and os.access(ceres, os.X_OK)):
            return None
        return [str(ceres), "--file", path, "--repeat", str(repeat)]
    lib, method = key.split("-")
    python = VENVS / lib / "bin" / "python"
    if not python.exists():
        return None
    cmd = [str(python), str(REFERENCE_DIR / f"{lib}_solve.py"), "--file", path,
           "--method", method, "--repeat", str(repeat)]
    if lib == "gtsam" and ds.dim == 3:
        cmd += ["--se3-info", "g2o"]
    return cmd


# ---------------------------------------------------------------------------------------------
# evaluation and reporting
# ---------------------------------------------------------------------------------------------

def usable(r: Optional[Dict[str, Any]]) -> bool:
    return bool(r) and not r.get("error") and bool(r.get("converged")) and r.get("solve_seconds") is not None


def comparable_chi2(r: Dict[str, Any], dim: int) -> Optional[float]:
    v = r.get("final_chi2_g2o")
    if v is None and dim == 2:
        v = r.get("final_chi2")
    return v if isinstance(v, (int, float)) and math.isfinite(v) else None


def evaluate(ds: Dataset, results: Dict[str, Dict[str, Any]]) -> Dict[str, Any]:
    refs = {k: r for k, r in results.items() if k != "factord" and usable(r)}
    fastest = min(refs, key=lambda k: refs[k]["solve_seconds"]) if refs else None
    f = results.get("factord")
    ratio = None
    if fastest and f and f.get("solve_seconds") and not f.get("error"):
        ratio = f["solve_seconds"] / refs[fastest]["solve_seconds"]

    tol = TOLERANCE[ds.dim]
    agreement: Dict[str, Optional[float]] = {}
    f_chi2 = comparable_chi2(f, ds.dim) if f and not f.get("error") else None
    if f_chi2 is not None:
        for k, r in refs.items():
            c = comparable_chi2(r, ds.dim)
            agreement[k] = None if c is None else (f_chi2 - c) / max(abs(c), 1e-300)
    bad = {k: d for k, d in agreement.items() if d is not None and abs(d) > tol}
    if f_chi2 is None:
        text = "n/a (no factord result)" if not f or f.get("error") else "n/a (no chi2)"
    elif not agreement:
        text = "n/a (no converged reference)"
    elif not bad:
        text = f"OK (max rel {max(abs(d) for d in agreement.values() if d is not None):.1e})"
    else:
        text = "; ".join(f"{SYSTEMS[k]} {d:+.2e}" for k, d in bad.items())
        text += " (factord lower)" if all(d < 0 for d in bad.values()) else ""
    if f_chi2 is not None and f and not f.get("converged"):
        text = "factord not converged; " + text
    return {"fastest": fastest, "ratio": ratio, "relative_chi2_diff": agreement,
            "tolerance": tol, "agreement": text}


def cell(r: Optional[Dict[str, Any]]) -> str:
    if r is None:
        return "-"
    if r.get("error"):
        return "FAIL" if r.get("solve_seconds") is None else f"{1e3 * r['solve_seconds']:.1f} FAIL"
    ms = r.get("solve_seconds")
    text = "?" if ms is None else f"{1e3 * ms:.1f}"
    return text if r.get("converged") else f"{text} (nc)"


def table_rows(report: List[Dict[str, Any]]) -> List[List[str]]:
    rows = []
    for entry in report:
        res, ev = entry["results"], entry["evaluation"]
        row = [entry["dataset"]] + [cell(res.get(k)) for k in SYSTEMS]
        row += [SYSTEMS[ev["fastest"]] if ev["fastest"] else "-",
                f"{ev['ratio']:.2f}" if ev["ratio"] is not None else "-",
                ev["agreement"]]
        rows.append(row)
    return rows


HEADER = ["dataset"] + [f"{h} ms" for h in SYSTEMS.values()] + ["fastest ref", "factord/fastest",
                                                                 "optimum agreement"]


def format_text(rows: List[List[str]]) -> str:
    widths = [max(len(r[i]) for r in rows + [HEADER]) for i in range(len(HEADER))]
    fmt = lambda r: "  ".join(c.ljust(w) if i in (0, len(r) - 1) else c.rjust(w)
                              for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([fmt(HEADER), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows])


def format_markdown(rows: List[List[str]], report: List[Dict[str, Any]], repeat: int) -> str:
    out = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    out += ["", f"Median solve time over {repeat} runs, in ms. `(nc)` = did not converge, "
                "`FAIL` = error; both are excluded from \"fastest ref\" and from the agreement check.",
            "Agreement: relative difference of factord's chi2 (g2o convention) from each converged "
            "reference's; tolerance 1e-6 (2D) / 1e-3 (3D).", "", "Final chi2 (g2o convention) and (iterations):", "",
            "| dataset | " + " | ".join(SYSTEMS.values()) + " |", "|---|" + "---|" * len(SYSTEMS)]
    for entry in report:
        cells = []
        for k in SYSTEMS:
            r = entry["results"].get(k)
            c = comparable_chi2(r, entry["dim"]) if r else None
            cells.append("-" if r is None else
                         ("FAIL" if r.get("error") else
                          f"{c:.6f} ({r.get('iterations')}{'' if r.get('converged') else ', nc'})" if c is not None
                          else "?"))
        out.append(f"| {entry['dataset']} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------

def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--factord", type=Path, default=DEFAULT_FACTORD, help=f"factord binary ({DEFAULT_FACTORD})")
    p.add_argument("--factord-args", default="", help="extra arguments for `factord solve`, e.g. '--method gn'")
    p.add_argument("--ceres", type=Path, default=DEFAULT_CERES, help=f"Ceres driver ({DEFAULT_CERES})")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help=f"data directory ({DEFAULT_DATA})")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--rounds", type=int, default=1,
                   help="run every system this many times per dataset, interleaved, and take the median over "
                        "all rounds' runs (spreads slow periods of a shared machine over all systems)")
    p.add_argument("--only", default="", help="comma-separated dataset names: " + ",".join(d.name for d in DATASETS))
    p.add_argument("--systems", default=",".join(SYSTEMS), help="comma-separated subset of: " + ",".join(SYSTEMS))
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per driver invocation (all repeats)")
    p.add_argument("--markdown", type=Path, help="write the table as Markdown")
    p.add_argument("--json", type=Path, help="write all raw results as JSON")
    args = p.parse_args()

    datasets = DATASETS
    if args.only:
        wanted = [s.strip() for s in args.only.split(",") if s.strip()]
        unknown = set(wanted) - {d.name for d in DATASETS}
        if unknown:
            p.error(f"unknown dataset(s): {', '.join(sorted(unknown))}")
        datasets = [d for d in DATASETS if d.name in wanted]
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    if set(systems) - set(SYSTEMS):
        p.error(f"unknown system(s): {', '.join(sorted(set(systems) - set(SYSTEMS)))}")

    if "factord" in systems and not (args.factord.is_file() and os.access(args.factord, os.X_OK)):
        log(f"[skip] factord: binary not found at {args.factord} (cargo build --release, or --factord PATH)")
        systems.remove("factord")
    if "ceres" in systems and not (args.ceres.is_file() and os.access(args.ceres, os.X_OK)):
        log(f"[skip] ceres: driver not found at {args.ceres} (benches/reference/ceres/build.sh, or --ceres PATH)")
        systems.remove("ceres")
    for lib in ("g2o", "gtsam"):
        if any(s.startswith(lib + "-") for s in systems) and not (VENVS / lib / "bin" / "python").exists():
            log(f"[skip] {lib}: no venv at {VENVS / lib} (run benches/reference/setup.sh)")
            systems = [s for s in systems if not s.startswith(lib + "-")]

    report = []
    for ds in datasets:
        missing = [f for f in (ds.factord_file, ds.factord_edges, ds.reference_file) if f and not (args.data / f).exists()]
        if missing:
            log(f"[skip] {ds.name}: missing {', '.join(missing)} under {args.data}")
            continue
        results: Dict[str, Dict[str, Any]] = {}
        for key in [k for _ in range(max(1, args.rounds)) for k in systems]:
            log(f"[run ] {ds.name:<20} {SYSTEMS[key]}")
            if key == "factord":
                r = run_factord(args.factord, ds, args.data, args.repeat, shlex.split(args.factord_args), args.timeout)
            else:
                cmd = reference_command(key, ds, args.data, args.repeat, args.ceres)
                if cmd is None:
                    r = error_result(key, "not available")
                else:
                    r = run_json(cmd, key, args.timeout)
                    r["command"] = " ".join(shlex.quote(c) for c in cmd)
            chi2 = comparable_chi2(r, ds.dim)
            log(f"       -> {cell(r)} ms, chi2 {chi2 if chi2 is not None else '-'}, "
                f"iterations {r.get('iterations', '-')}{', error: ' + r['error'] if r.get('error') else ''}")
            previous = results.get(key)
            if previous and not previous.get("error") and not r.get("error"):
                # Later rounds pool their runs into the first result.
                runs = previous.get("solve_seconds_runs", []) + r.get("solve_seconds_runs", [])
                previous["solve_seconds_runs"] = runs
                previous["solve_seconds"] = statistics.median(runs)
            elif previous is None or r.get("error"):
                results[key] = r
        report.append({"dataset": ds.name, "dim": ds.dim, "results": results,
                       "evaluation": evaluate(ds, results)})

    rows = table_rows(report)
    print(format_text(rows))
    if args.markdown:
        args.markdown.write_text(format_markdown(rows, report, args.repeat))
        log(f"wrote {args.markdown}")
    if args.json:
        args.json.write_text(json.dumps({"repeat": args.repeat, "data": str(args.data), "datasets": report},
                                        indent=2) + "\n")
        log(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
