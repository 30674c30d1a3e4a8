#!/usr/bin/env python3
"""A scripted robot: streams a pose graph to factord over zenoh, pose by pose, as a robot's
front-end would, and prints live statistics from the session's published events.

    python clients/python/examples/robot.py --zenoh tcp/127.0.0.1:7447 --limit 500 --rate 100

Each pose is one batch on ``factord/<session>/in/batch``: the new pose (its value left out when an
odometry edge joins it to the previous pose, so the server predicts it) and every edge that ends
at it (odometry and loop closures). Batches go through a :class:`StreamProducer`: numbered
(``producer``/``producer_seq``), kept until acknowledged and resent after a timeout, a
reconnection or a restart of the service, so each is applied exactly once. The robot listens on
``out/acks``, ``out/stats``, ``out/summary`` (and ``out/errors``), prints live statistics
(acknowledged batches, the session sequence the estimate reflects, solves), waits until every
batch is acknowledged, asks for a final solve that comes after its batches (``after_seq``),
reads the estimate back as a numpy array (``estimate_array``: (N, 3) for 2D, (N, 7) for 3D) and
checks that the service holds exactly the poses and factors it sent; ``--tum FILE`` saves the
trajectory (the estimate queryable's ``format=tum``). Exits non-zero when a batch was refused,
the server does not answer, or the counts differ.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

try:
    from factord_client import BatchRefused, FactordError, ZenohClient, g2o, gtsam_text
except ImportError:  # running from a checkout without `pip install`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from factord_client import BatchRefused, FactordError, ZenohClient, g2o, gtsam_text

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
    """What the subscriptions have seen so far (updated from zenoh threads). Every number is
    cumulative on the wire, so a missed or coalesced event cannot make it wrong: acknowledged
    batches come from the producer's ``accepted_through``, the reflected sequence from the
    largest ``reflected`` ack / ``summary`` / ``lagged`` sequence, solves from the ``solve``
    number of the latest summary."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.sequence = 0  # latest session sequence acknowledged
        self.reflected = 0  # session sequence the estimate reflects
        self.predicted = set()
        self.chi2 = None
        self.solves = 0
        self.last_solve_seconds = None
        self.lagged = 0

    def on_ack(self, event: dict) -> None:  # this producer's acks (StreamProducer's on_ack)
        with self.lock:
            self.sequence = max(self.sequence, event["sequence"])
            if event.get("reflected"):
                self.reflected = max(self.reflected, event["sequence"])
            self.predicted.update(event.get("predicted", []))

    def on_any_ack(self, event: dict) -> None:  # out/acks: also lagged markers
        if event.get("type") == "lagged":
            with self.lock:
                self.lagged += 1
                self.sequence = max(self.sequence, event.get("sequence", 0))
                self.reflected = max(self.reflected, event.get("reflected_sequence", 0))

    def on_stats(self, event: dict) -> None:  # one solver iteration (may be dropped)
        if event.get("type") == "iteration" and event.get("accepted", True):
            with self.lock:
                self.chi2 = event["chi2"]

    def on_summary(self, event: dict) -> None:
        if event.get("type") == "lagged":
            with self.lock:
                self.reflected = max(self.reflected, event.get("reflected_sequence", 0))
            return
        if event.get("type") != "summary":
            return
        summary = event["summary"]
        with self.lock:
            self.solves = max(self.solves, event.get("solve", self.solves + 1))
            self.reflected = max(self.reflected, event.get("sequence", 0))
            self.chi2 = summary["final_chi2"]
            self.last_solve_seconds = summary["solve_seconds"]

    def on_error(self, event: dict) -> None:
        if event.get("type") != "error" or event.get("producer"):
            return  # this producer's refusals are raised by the producer itself
        error = event.get("error", {})
        print(f"  ! error (sequence {event.get('sequence')}): {error.get('code')}"
              f" at {error.get('field')}: {error.get('message')}", file=sys.stderr)

    def line(self, producer) -> str:
        c = producer.counters
        with self.lock:
            chi2 = "-" if self.chi2 is None else f"{self.chi2:.6g}"
            solve = ("-" if self.last_solve_seconds is None
                     else f"{self.last_solve_seconds * 1e3:.1f} ms")
            return (f"sent {c['sent']:6d}  acked {c['acked']:6d}  reflected seq "
                    f"{self.reflected:6d}/{self.sequence:<6d}  solves {self.solves:5d}  "
                    f"chi2 {chi2:>12}  last solve {solve:>9}  resent {c['resent']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", nargs="?",
                        help=f"g2o file or GTSAM landmark text (victoria_park.txt), absolute or "
                             f"relative to --data-dir; default "
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
    parser.add_argument("--producer", default=None,
                        help="producer id (default: <hostname>-<session>)")
    parser.add_argument("--window", type=int, default=1024,
                        help="most unacknowledged batches in flight (send blocks beyond)")
    parser.add_argument("--resend-after", type=float, default=2.0,
                        help="seconds without acknowledgement or progress before resending")
    parser.add_argument("--tum", type=Path, default=None,
                        help="write the optimised trajectory here (TUM: stamp tx ty tz qx qy qz "
                             "qw; the stamps are the keys, g2o files have no time)")
    args = parser.parse_args(argv)

    data_dir = args.data_dir or default_data_dir()
    path = resolve_dataset(args.dataset, data_dir)
    if not path.exists():
        print(f"robot: dataset {path} not found (use --data-dir or a path)", file=sys.stderr)
        return 2
    graph = gtsam_text.load(path) if gtsam_text.is_gtsam_text(path) else g2o.load(path)
    batches = list(graph.batches(predict=not args.no_predict, limit=args.limit))
    session = args.session or f"robot-{os.getpid()}"
    policy, _, number = args.auto_optimize.partition(":")
    auto: dict = {"policy": policy}
    if policy == "every_n_factors":
        auto["factors"] = int(number or 100)
    elif policy == "every_ms":
        auto["milliseconds"] = int(number or 100)

    factors_sent = sum(len(b["factors"]) for _, b in batches)
    print(f"robot: {path.name}: {len(graph.vertices)} variables, {len(graph.edges)} factors; streaming "
          f"{len(batches)} poses ({factors_sent} factors) to session `{session}` over "
          f"{args.zenoh}")
    live = Live()
    sent_keys = np.array(sorted(v["key"] for _, b in batches for v in b.get("variables", [])),
                         dtype=np.int64)
    try:
        client = ZenohClient(args.zenoh, prefix=args.prefix, mode=args.mode,
                             timeout=args.timeout)
    except FactordError as e:  # zenoh's own errors arrive as FactordConnectionError
        print(f"robot: cannot open zenoh towards {args.zenoh}: {e}", file=sys.stderr)
        return 2
    producer = None
    # The client closes zenoh on exit even without `with`; `with` closes it right here.
    with client:
        return _stream(args, client, live, graph, batches, session, auto, sent_keys,
                       factors_sent, path)


def _stream(args: argparse.Namespace, client: ZenohClient, live: Live, graph, batches: list,
            session: str, auto: dict, sent_keys: np.ndarray, factors_sent: int,
            path: Path) -> int:
    producer = None
    try:
        # Subscribe before the session exists so that no event is missed.
        client.subscribe(session, "acks", live.on_any_ack)
        client.subscribe(session, "stats", live.on_stats)
        client.subscribe(session, "summary", live.on_summary)
        client.subscribe(session, "errors", live.on_error)
        created = client.create_session(graph.session_kind, session=session, auto_optimize=auto)
        print(f"robot: created {created['session']} ({created['kind']}, "
              f"auto_optimize {created['auto_optimize']})")
        producer = client.producer(session, args.producer, window=args.window,
                                   resend_after=args.resend_after, on_ack=live.on_ack)

        start = time.monotonic()
        for sent, (_key, batch) in enumerate(batches, start=1):
            if args.rate > 0:
                delay = start + (sent - 1) / args.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            producer.send(batch)
            if sent % args.every == 0:
                print("  " + live.line(producer), flush=True)
        elapsed = time.monotonic() - start
        producer.flush(args.timeout)
        acked_after = time.monotonic() - start
        c = producer.counters
        print(f"robot: {len(batches)} poses streamed in {elapsed:.2f} s "
              f"({len(batches) / max(elapsed, 1e-9):.0f} poses/s), all {c['acked']} "
              f"acknowledged after {acked_after:.2f} s (producer {producer.producer}, "
              f"seq {producer.accepted_through}; {c['resent']} resent, {c['duplicates']} "
              f"duplicate acks, {c['lagged']} lagged markers); {len(live.predicted)} "
              f"predicted by the server in the {c['acks']} ack events seen")
        print("  " + live.line(producer))

        stats = producer.optimize(wait=True, timeout=args.timeout)["stats"]
        print(f"robot: final solve: chi2 {stats['chi2']:.6f}  ({stats['num_variables']} poses, "
              f"{stats['num_factors']} factors, {stats['solves']} solves, "
              f"{stats['skipped_solves']} skipped, converged {stats['converged']})")
        print(f"final chi2 {stats['chi2']:.9g}")
        estimate = client.estimate_array(session)  # the poses; landmarks are kind="point2"
        held_keys = np.sort(np.concatenate(
            [estimate.keys] + [client.estimate_array(session, kind=k).keys
                               for k in estimate.extra_kinds]))
        last = estimate.poses()[int(estimate.keys[-1])] if len(estimate) else None
        print(f"robot: estimate {estimate.kind} {estimate.values.shape}, last pose {last}")
        if stats["num_factors"] != factors_sent or stats["num_variables"] != len(sent_keys) \
                or not np.array_equal(held_keys, sent_keys):
            print(f"robot: the service holds {stats['num_variables']} variables and "
                  f"{stats['num_factors']} factors; sent {len(sent_keys)} and {factors_sent}",
                  file=sys.stderr)
            return 1
        if args.tum is not None:
            args.tum.write_text(client.export(session, "tum"))
            print(f"robot: trajectory written to {args.tum}")
        if args.delete:
            client.delete_session(session)
        return 0
    except BatchRefused as e:
        print(f"robot: stopped: {e}", file=sys.stderr)
        return 1
    except FactordError as e:
        print(f"robot: {e}", file=sys.stderr)
        return 1
    finally:
        if producer is not None:
            producer.close()


if __name__ == "__main__":
    sys.exit(main())
