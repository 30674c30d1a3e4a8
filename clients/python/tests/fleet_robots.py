#!/usr/bin/env python3
"""Robots of a factord fleet: one process, one StreamProducer per robot session, paced.

Driven by tests/fleet/fleet_robots.rs, which starts three `factord serve --fleet` instances, writes one
g2o graph per robot, runs this script, kills (-9) an instance mid-stream and checks the results:

    python clients/python/tests/fleet_robots.py --http URL1,URL2,URL3 --zenoh EP1,EP2,EP3 \
        --graphs DIR --rate 60 --out result.json

* Each robot `robot-NN` (a file `robot-NN.g2o` in DIR) creates its session over HTTP through
  instance NN % 3 (placement puts it on its owner), then streams its batches (one pose with its
  edges each, at `--rate` batches/s) through its own `ZenohClient` given every instance's
  endpoint, its "home" instance NN % 3 first: zenoh connects to one of them and moves to another
  when that one dies.
* stdout: `progress <seconds> <least batches acknowledged by one robot> <acked> <sent>` every
  100 ms while streaming, then one `result <json>` line.
* stdin: the test writes `killed <index> <session,session,...>` when it killed an instance (then
  the script asks only the survivors over HTTP) and the sessions that instance owned (for the
  robot's view of the outage: time from the kill to the session's next new acknowledgement).
* At the end: every producer flushes (every batch acknowledged), asks `optimize(wait=True)`
  after its batches and reads the estimate after them; the server's counts are read over HTTP.
  The result carries, per robot, the producer's counters, accepted_through, the server's
  num_factors/num_variables/sequence, the solved chi2 and the estimate (key -> [x, y, theta]).
* `--no-resend`: producers never send a batch twice (their resending step disabled): the test
  must then fail (what it is for).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve()
sys.path.insert(0, str(HERE.parents[1]))
from factord_client import HttpClient, ZenohClient, g2o  # noqa: E402


class Robot:
    def __init__(self, index: int, path: Path) -> None:
        self.index = index
        self.session = path.stem
        self.producer_id = f"{self.session}-p"
        self.graph = g2o.load(path)
        self.batches = [b for _, b in self.graph.batches(predict=True)]
        self.ack_times: list = []  # monotonic times of new (not duplicate) acknowledgements
        self.refusals: dict = {}  # error code -> count of this producer's batches refused
        self.lock = threading.Lock()
        self.producer = None
        self.client = None
        self.result: dict = {"session": self.session, "producer": self.producer_id,
                             "batches": len(self.batches), "edges": len(self.graph.edges),
                             "vertices": len(self.graph.vertices)}
        self.error = None

    def on_error(self, event: dict) -> None:
        if event.get("type") == "error" and event.get("producer") == self.producer_id:
            code = (event.get("error") or {}).get("code", "?")
            with self.lock:
                self.refusals[code] = self.refusals.get(code, 0) + 1

    def on_ack(self, event: dict) -> None:
        if not event.get("duplicate"):
            with self.lock:
                self.ack_times.append(time.monotonic())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--http", required=True, help="the instances' HTTP URLs, comma-separated")
    parser.add_argument("--zenoh", required=True, help="their zenoh endpoints, comma-separated")
    parser.add_argument("--graphs", type=Path, required=True, help="robot-NN.g2o files")
    parser.add_argument("--rate", type=float, default=60.0, help="batches/s per robot")
    parser.add_argument("--resend-after", type=float, default=0.5)
    parser.add_argument("--max-resend-after", type=float, default=2.0)
    parser.add_argument("--no-resend", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    urls = args.http.split(",")
    endpoints = args.zenoh.split(",")
    n = len(urls)
    alive = list(range(n))
    killed: dict = {}
    t0 = time.monotonic()

    def stdin_reader() -> None:
        for line in sys.stdin:
            parts = line.split()
            if parts and parts[0] == "killed":
                index = int(parts[1])
                killed["at"] = time.monotonic()
                killed["index"] = index
                killed["sessions"] = parts[2].split(",") if len(parts) > 2 else []
                if index in alive:
                    alive.remove(index)

    threading.Thread(target=stdin_reader, daemon=True).start()

    def http() -> HttpClient:
        # Any surviving instance answers for any session (forwarded to its owner).
        return HttpClient(urls[alive[0]], timeout=60, retries=40, max_retry_wait=0.5,
                          retry_budget=60)

    robots = [Robot(i, p) for i, p in enumerate(sorted(args.graphs.glob("robot-*.g2o")))]
    for r in robots:
        HttpClient(urls[r.index % n], timeout=30).create_session(
            r.graph.session_kind, session=r.session, auto_optimize="manual",
            options={"function_tolerance": 1e-12})
    options = {"resend_after": args.resend_after, "max_resend_after": args.max_resend_after,
               "on_ack": None}
    for r in robots:
        home = r.index % n
        r.client = ZenohClient([endpoints[(home + k) % n] for k in range(n)], timeout=30)
        r.client.subscribe(r.session, "errors", r.on_error)  # what the producer is told
        r.producer = r.client.producer(r.session, r.producer_id, window=4096,
                                       **{**options, "on_ack": r.on_ack})
        if args.no_resend:
            # The resending step (timer, reconnection, gap, Retry-After) does nothing.
            r.producer._step = lambda now: None
    setup_s = time.monotonic() - t0

    done = threading.Event()

    def stream(r: Robot) -> None:
        try:
            start = time.monotonic()
            for k, batch in enumerate(r.batches):
                r.producer.send(batch, timeout=60)
                pause = start + (k + 1) / args.rate - time.monotonic()
                if pause > 0:
                    time.sleep(pause)
            r.result["send_s"] = time.monotonic() - start
            r.producer.flush(timeout=45)
            r.result["flushed_s"] = time.monotonic() - start
        except Exception as e:  # noqa: BLE001 - reported in the result
            r.error = f"stream: {e!r}"
            traceback.print_exc(file=sys.stderr)

    def progress() -> None:
        while not done.is_set():
            acked = [r.producer.accepted_through for r in robots]
            sent = sum(r.producer.last_seq for r in robots)
            print(f"progress {time.monotonic() - t0:.2f} {min(acked)} {sum(acked)} {sent}",
                  flush=True)
            done.wait(0.1)

    stream_t0 = time.monotonic()
    threads = [threading.Thread(target=stream, args=(r,), daemon=True) for r in robots]
    reporter = threading.Thread(target=progress, daemon=True)
    reporter.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stream_s = time.monotonic() - stream_t0
    done.set()
    reporter.join()

    # The final answers, after each producer's batches.
    def finish(r: Robot) -> None:
        if r.error:
            return
        try:
            p = r.producer
            solved = p.optimize(wait=True, timeout=60)
            estimate = p.estimate(timeout=60)
            stats = http().stats(r.session)
            r.result.update({
                "counters": dict(p.counters),
                "accepted_through": p.accepted_through,
                "sent": p.last_seq,
                "chi2": solved["stats"]["chi2"],
                "num_factors": stats["num_factors"],
                "num_variables": stats["num_variables"],
                "sequence": stats["sequence"],
                "estimate": {str(v["key"]): v["value"] for v in estimate["variables"]},
            })
            with r.lock:
                times = list(r.ack_times)
                r.result["refusals"] = dict(r.refusals)
            if times:
                gaps = [b - a for a, b in zip(times, times[1:])]
                r.result["max_ack_gap_s"] = max(gaps, default=0.0)
            if "at" in killed and r.session in killed["sessions"]:
                after = [t for t in times if t >= killed["at"]]
                r.result["acks_resumed_s"] = (after[0] - killed["at"]) if after else None
        except Exception as e:  # noqa: BLE001
            r.error = f"finish: {e!r}"
            traceback.print_exc(file=sys.stderr)

    finish_t0 = time.monotonic()
    threads = [threading.Thread(target=finish, args=(r,), daemon=True) for r in robots]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    finish_s = time.monotonic() - finish_t0
    for r in robots:
        r.producer.close()
        r.client.close()
        if r.error:
            r.result["error"] = r.error
    out = {"setup_s": setup_s, "stream_s": stream_s, "finish_s": finish_s,
           "killed": {k: v for k, v in killed.items() if k != "at"},
           "killed_at_s": killed["at"] - t0 if "at" in killed else None,
           "robots": [r.result for r in robots]}
    args.out.write_text(json.dumps(out))
    errors = [r.error for r in robots if r.error]
    print(f"result {len(robots)} robots, {len(errors)} errors, stream {stream_s:.1f} s, "
          f"finish {finish_s:.1f} s", flush=True)
    for e in errors:
        print(f"error {e}", flush=True)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
