"""Acknowledgement latency of small batches into a big durable session while snapshots are written
(issue 16, item 4): a 2D pose graph of --poses poses (odometry plus a loop closure every 50 poses,
so about 1.02 factors per pose) is loaded in large batches, then --updates single-pose batches are
posted one after the other with `?wait=true` over one keep-alive connection (manual policy: no
solve runs, so what is measured is validation, the journal's fsync, the lock, the statistics a
`wait` answer reads, and the snapshot every --snapshot-every entries). Client-measured latency per
batch: p50, p99, p99.9, worst, and the slowest batches with their sequence numbers.

    python3 benches/durability/snapshot_latency.py BINARY [BINARY ...] [--poses 100000]
        [--updates 6000] [--snapshot-every 2000] [--fsync always|interval|never] [--json out.json]

Several binaries (say one built before a change and one after) run one after the other on the same
inputs.
"""
import argparse, http.client, json, math, os, random, shutil, signal, subprocess, tempfile, time


def start(binary, state, config):
    p = subprocess.Popen([binary, "serve", "--listen", "127.0.0.1:0", "--no-zenoh", "--state-dir", state,
                          "--config", config, "--log", "warn"], stderr=subprocess.DEVNULL)
    info = os.path.join(state, "server.json")
    deadline = time.time() + 30
    while time.time() < deadline:
        try:
            host, port = json.load(open(info))["http"].rsplit(":", 1)
            return p, host, int(port)
        except (FileNotFoundError, ValueError):
            time.sleep(0.01)
    p.kill()
    raise SystemExit(f"{binary} did not start")


class Client:
    def __init__(self, host, port):
        self.c = http.client.HTTPConnection(host, port, timeout=600)

    def call(self, method, path, body=None):
        data = None if body is None else json.dumps(body).encode()
        self.c.request(method, path, body=data, headers={"content-type": "application/json"})
        r = self.c.getresponse()
        payload = r.read()
        if r.status != 200 and r.status != 201:
            raise SystemExit(f"{method} {path}: {r.status} {payload[:300]}")
        return json.loads(payload)


def pose_batch(first, last, rng):
    """Poses first..last-1 (values along a noisy walk), odometry into each, a closure every 50."""
    variables, factors = [], []
    for k in range(first, last):
        v = {"key": k, "kind": "se2", "value": [float(k % 1000), float(k // 1000), 0.0]}
        if k == 0:
            v["fixed"] = True
        variables.append(v)
        if k > 0:
            factors.append({"type": "between_se2", "keys": [k - 1, k],
                            "measurement": [1.0 + rng.gauss(0, 0.01), rng.gauss(0, 0.01), rng.gauss(0, 0.001)],
                            "sigmas": [0.05, 0.05, 0.01]})
        if k >= 100 and k % 50 == 0:
            factors.append({"type": "between_se2", "keys": [k - 100, k],
                            "measurement": [100.0, 0.0, 0.0], "sigmas": [0.5, 0.5, 0.1]})
    return {"variables": variables, "factors": factors}


def percentile(sorted_ms, p):
    return sorted_ms[min(len(sorted_ms) - 1, int(round((len(sorted_ms) - 1) * p)))]


def run(binary, a):
    work = tempfile.mkdtemp(prefix="factord-snaplat-")
    state, config = os.path.join(work, "state"), os.path.join(work, "config.json")
    json.dump({"journal": {"snapshot_every": a.snapshot_every, "fsync": a.fsync}}, open(config, "w"))
    p, host, port = start(binary, state, config)
    try:
        c = Client(host, port)
        c.call("POST", "/v1/sessions", {"session": "big", "kind": "pose_graph_2d",
                                        "auto_optimize": {"policy": "manual"}})
        rng = random.Random(7)
        t = time.time()
        for first in range(0, a.poses, 10000):
            c.call("POST", "/v1/sessions/big/batches", pose_batch(first, min(a.poses, first + 10000), rng))
        load = time.time() - t
        stats = c.call("GET", "/v1/sessions/big")
        sequence0 = stats["sequence"]
        lat, seqs = [], []
        for i in range(a.updates):
            k = a.poses + i
            body = pose_batch(k, k + 1, rng)
            t = time.perf_counter()
            ack = c.call("POST", "/v1/sessions/big/batches?wait=true", body)
            ms = (time.perf_counter() - t) * 1e3
            lat.append(ms)
            seqs.append(ack["sequence"])
        stats = c.call("GET", "/v1/sessions/big")
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
        shutil.rmtree(work, ignore_errors=True)
    s = sorted(lat)
    return {
        "binary": binary, "poses": a.poses, "factors": stats["num_factors"], "updates": a.updates,
        "first_update_sequence": sequence0 + 1, "snapshot_every": a.snapshot_every, "fsync": a.fsync,
        "load_seconds": round(load, 2), "memory_bytes": stats.get("memory_bytes"),
        "p50_ms": round(percentile(s, 0.5), 3), "p99_ms": round(percentile(s, 0.99), 3),
        "p999_ms": round(percentile(s, 0.999), 3), "worst_ms": round(s[-1], 3),
        "mean_ms": round(sum(s) / len(s), 3),
        # Snapshots start every --snapshot-every journal entries: the slowest batches show them.
        "slowest": [[q, round(ms, 2)] for ms, q in sorted(zip(lat, seqs), reverse=True)[:6]],
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binaries", nargs="+")
    ap.add_argument("--poses", type=int, default=100000)
    ap.add_argument("--updates", type=int, default=6000)
    ap.add_argument("--snapshot-every", type=int, default=2000)
    ap.add_argument("--fsync", default="always")
    ap.add_argument("--json")
    a = ap.parse_args()
    results = [run(b, a) for b in a.binaries]
    print("| binary | factors | p50 ms | p99 ms | p99.9 ms | worst ms | slowest [sequence, ms] |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['binary']} | {r['factors']} | {r['p50_ms']} | {r['p99_ms']} | {r['p999_ms']} | "
              f"{r['worst_ms']} | {r['slowest']} |")
    if a.json:
        json.dump(results, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
