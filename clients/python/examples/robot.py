#!/usr/bin/env python3
"""A scripted robot: streams a pose graph to factord over zenoh, pose by pose, as a robot's
front-end would, and prints live statistics from the session's published events.

    python clients/python/examples/robot.py --zenoh tcp/127.0.0.1:7447 --limit 500 --rate 100

Each pose is one batch on ``factord/<session>/in/batch``: the new pose (its value left out when an
odometry edge joins it to the previous pose, so the server predicts it) and every edge that ends
at it (odometry and loop closures). The robot listens on ``out/acks``, ``out/stats``,
``out/summary`` (and ``out/errors``) and, at the end, asks for a final solve over rpc and prints
the final chi2. Exits non-zero when a batch was rejected or the server does not answer.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

try:
    from factord_client import FactordError, ZenohClient, g2o
except ImportError:  # running from a checkout without `pip install`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from factord_client import FactordError, ZenohClient, g2o

REPO_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_DATASET = "2d/carlone/input_M3500_g2o.g2o"


def default_data_dir() -> Path:
    env = os.environ.get("FACTORD_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def resolve_dataset(path: str | None, data_dir: Path) -> Path:
    if path is None:
        return data_dir / DEFAULT_DATASET
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    return data_dir / p


class Live:
    """What the subscriptions have seen so far (updated from zenoh threads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.acked = 0
        self.predicted = 0
        self.iterations = 0
        self.chi2 = None
        self.solves = 0
        self.last_solve_seconds = None
        self.errors = []
        self.acked_event = threading.Condition(self.lock)

    def on_ack(self, event: dict) -> None:
        with self.lock:
            self.acked = max(self.acked, event["sequence"])
            self.predicted += len(event.get("predicted", []))
            self.acked_event.notify_all()

    def on_stats(self, event: dict) -> None:  # one solver iteration
        with self.lock:
            self.iterations += 1
            if event.get("accepted", True):
                self.chi2 = event["chi2"]

    def on_summary(self, event: dict) -> None:
        summary = event["summary"]
        with self.lock:
            self.solves += 1
            self.chi2 = summary["final_chi2"]
            self.last_solve_seconds = summary["solve_seconds"]

    def on_error(self, event: dict) -> None:
        error = event.get("error", {})
        with self.lock:
            self.errors.append(event)
            self.acked_event.notify_all()
        print(f"  ! error (sequence {event.get('sequence')}): {error.get('code')}"
              f" at {error.get('field')}: {error.get('message')}", file=sys.stderr)

    def wait_acked(self, sequence: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self.lock:
            while self.acked < sequence and not self.errors:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.acked_event.wait(left)
            return self.acked >= sequence

    def line(self, sent: int) -> str:
        with self.lock:
            chi2 = "-" if self.chi2 is None else f"{self.chi2:.6g}"
            solve = ("-" if self.last_solve_seconds is None
                     else f"{self.last_solve_seconds * 1e3:.1f} ms")
            return (f"poses sent {sent:6d}  acked seq {self.acked:6d}  solves {self.solves:5d}  "
                    f"chi2 {chi2:>12}  last solve {solve:>10}")


def final_solve(client: ZenohClient, session: str, timeout: float) -> dict:
    """Solve now and wait for that solve (rpc ``optimize`` with ``wait``); returns the stats."""
    return client.optimize(session, wait=True)["stats"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", nargs="?",
                        help=f"g2o file (absolute, or relative to --data-dir); default "
                             f"{DEFAULT_DATASET}")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="datasets folder (default: $FACTORD_DATA or ../shared/data from "
                             "the repository root)")
    parser.add_argument("--zenoh", default="tcp/127.0.0.1:7447",
                        help="zenoh endpoint of factord or of its router")
    parser.add_argument("--mode", choices=("client", "peer"), default="client")
    parser.add_argument("--prefix", default="factord", help="factord's zenoh key prefix")
    parser.add_argument("--session", default=None,
                        help="session name (default: robot-<pid>); must not exist yet")
    parser.add_argument("--limit", type=int, default=None, help="stream at most N poses")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="poses per second (0 = as fast as possible)")
    parser.add_argument("--every", type=int, default=100, help="print statistics every N poses")
    parser.add_argument("--no-predict", action="store_true",
                        help="send every pose's value from the file instead of letting the "
                             "server predict it from odometry")
    parser.add_argument("--auto-optimize", default="every_batch",
                        help="session policy: every_batch | manual | every_n_factors:N | "
                             "every_ms:MS")
    parser.add_argument("--delete", action="store_true", help="delete the session at the end")
    parser.add_argument("--timeout", type=float, default=120.0,
                        help="seconds to wait for acknowledgements and the final solve")
    args = parser.parse_args(argv)

    data_dir = args.data_dir or default_data_dir()
    path = resolve_dataset(args.dataset, data_dir)
    if not path.exists():
        print(f"robot: dataset {path} not found (use --data-dir or a path)", file=sys.stderr)
        return 2
    graph = g2o.load(path)
    batches = list(graph.batches(predict=not args.no_predict, limit=args.limit))
    session = args.session or f"robot-{os.getpid()}"
    policy, _, number = args.auto_optimize.partition(":")
    auto: dict = {"policy": policy}
    if policy == "every_n_factors":
        auto["factors"] = int(number or 100)
    elif policy == "every_ms":
        auto["milliseconds"] = int(number or 100)

    print(f"robot: {path.name}: {len(graph.vertices)} poses, {len(graph.edges)} edges; streaming "
          f"{len(batches)} poses to session `{session}` over {args.zenoh}")
    live = Live()
    try:
        client = ZenohClient(args.zenoh, prefix=args.prefix, mode=args.mode,
                             timeout=args.timeout)
    except Exception as e:  # noqa: BLE001 - zenoh raises its own error types
        print(f"robot: cannot open zenoh towards {args.zenoh}: {e}", file=sys.stderr)
        return 2
    try:
        # Subscribe before the session exists so that no event is missed.
        client.subscribe(session, "acks", live.on_ack)
        client.subscribe(session, "stats", live.on_stats)
        client.subscribe(session, "summary", live.on_summary)
        client.subscribe(session, "errors", live.on_error)
        created = client.create_session(graph.session_kind, session=session, auto_optimize=auto)
        print(f"robot: created {created['session']} ({created['kind']}, "
              f"auto_optimize {created['auto_optimize']})")

        start = time.monotonic()
        for sent, (_key, batch) in enumerate(batches, start=1):
            if args.rate > 0:
                delay = start + (sent - 1) / args.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            client.publish_batch(session, batch)
            if sent % args.every == 0 or sent == len(batches):
                print("  " + live.line(sent), flush=True)
            if live.errors:
                break
        elapsed = time.monotonic() - start
        if live.errors:
            print("robot: a batch was rejected; stopping", file=sys.stderr)
            return 1
        if not live.wait_acked(len(batches), args.timeout):
            print(f"robot: only {live.acked} of {len(batches)} batches acknowledged after "
                  f"{args.timeout:.0f} s", file=sys.stderr)
            return 1
        print(f"robot: {len(batches)} poses streamed in {elapsed:.2f} s "
              f"({len(batches) / max(elapsed, 1e-9):.0f} poses/s), all acknowledged; "
              f"{live.predicted} predicted by the server")
        print("  " + live.line(len(batches)))

        stats = final_solve(client, session, args.timeout)
        print(f"robot: final solve: chi2 {stats['chi2']:.6f}  ({stats['num_variables']} poses, "
              f"{stats['num_factors']} factors, {stats['solves']} solves, "
              f"{stats['skipped_solves']} skipped, converged {stats['converged']})")
        print(f"final chi2 {stats['chi2']:.9g}")
        if args.delete:
            client.delete_session(session)
        return 0
    except FactordError as e:
        print(f"robot: {e}", file=sys.stderr)
        return 1
    finally:
        client.close()


if __name__ == "__main__":
    sys.exit(main())
