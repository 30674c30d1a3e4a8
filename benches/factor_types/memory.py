#!/usr/bin/env python3
"""User-defined factor types: memory, create time and restart blackout.

N sessions each declare the same 32 definitions near the size bounds (MAX_COST: ~98k tape
slots with 3 tangent lanes each); prints RSS and the sessions' `memory_bytes` after the
creates, the create time, then kills the server (-9), restarts it on the same state directory
and port, and prints the time to the first `/health` answer and until every session is
writable again.

    python3 benches/factor_types/memory.py <factord binary> [sessions=10] [types=32] [distinct]

With `distinct`, each session's definitions are its own (other names): nothing is shared, and
the server's bound on distinct compiled types (limits.max_factor_type_bytes) is what stops it.
"""
import json, os, random, shutil, signal, socket, subprocess, sys, tempfile, time
import requests

LEAVES = 188  # 2 x 256 slots each: ~98k slots x (1 + 3 lanes) under MAX_COST = 400k


def heavy_definition(i, prefix="heavy"):
    rng = random.Random(i)
    x = {"mul": [{"at": [{"translation": ["a"]}, 0]}, "m"]}
    leaves = [{"mul": [round(rng.uniform(0.5, 1.5), 9), x]} for _ in range(LEAVES)]
    while len(leaves) > 1:  # a balanced sum: depth log2(LEAVES)
        leaves = [{"add": leaves[k:k + 2]} if k + 1 < len(leaves) else leaves[k]
                  for k in range(0, len(leaves), 2)]
    return {"name": f"{prefix}_{i}",
            "variables": [{"name": "a", "kind": "se2"}],
            "parameters": [{"name": "m", "kind": "vector", "len": 256}],
            "residual": {"norm": [leaves[0]]}}


def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p


def rss_mb(pid):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024


def start(binary, state, port):
    log = open(state + ".stderr", "a")
    p = subprocess.Popen([binary, "serve", "--listen", f"127.0.0.1:{port}",
                          "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}",
                          "--zenoh-multicast", "off", "--state-dir", state],
                         stdout=subprocess.DEVNULL, stderr=log)
    t0 = time.monotonic()
    while True:
        try:
            if requests.get(f"http://127.0.0.1:{port}/v1/health", timeout=0.5).status_code == 200:
                return p, time.monotonic() - t0
        except requests.RequestException:
            pass
        if p.poll() is not None:
            sys.exit("server exited: " + open(state + ".stderr").read()[-2000:])
        time.sleep(0.01)


def main():
    binary = sys.argv[1]
    sessions = int(sys.argv[2]) if len(sys.argv) > 2 else 10
    types = int(sys.argv[3]) if len(sys.argv) > 3 else 32
    distinct = len(sys.argv) > 4 and sys.argv[4] == "distinct"
    definitions = [heavy_definition(i) for i in range(types)]
    state = tempfile.mkdtemp(prefix="types-bench-")
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    p, _ = start(binary, state, port)
    print(f"RSS idle: {rss_mb(p.pid):.0f} MB")
    body_kb = len(json.dumps({"kind": "pose_graph_2d", "factor_types": definitions})) / 1024
    print(f"create body: {body_kb:.0f} KB ({types} definitions)")
    times = []
    for s in range(sessions):
        if distinct:
            definitions = [heavy_definition(i, f"s{s}") for i in range(types)]
        t0 = time.monotonic()
        r = requests.post(f"{base}/v1/sessions", json={
            "session": f"t{s}", "kind": "pose_graph_2d", "factor_types": definitions},
            timeout=600)
        times.append(time.monotonic() - t0)
        if r.status_code != 201:
            print(f"create t{s}: {r.status_code} after {times.pop():.2f} s, RSS "
                  f"{rss_mb(p.pid):.0f} MB: {r.text[:300]}")
            break
        batch = {"variables": [{"key": k, "kind": "se2", "value": [k, 0, 0]} for k in range(3)],
                 "factors": [{"type": definitions[0]["name"], "keys": [0], "measurement": [0.01] * 256,
                              "information": [1.0]}]}
        r = requests.post(f"{base}/v1/sessions/t{s}/batches", json=batch, timeout=60)
        assert r.status_code == 200, r.text
        print(f"  session {s}: create {times[-1]:.2f} s, RSS {rss_mb(p.pid):.0f} MB")
    made = len(times)
    mem = sum(requests.get(f"{base}/v1/sessions/t{s}").json()["memory_bytes"] for s in range(made))
    print(f"after {made} sessions: RSS {rss_mb(p.pid):.0f} MB, sum of memory_bytes "
          f"{mem / 2**20:.1f} MiB, creates {sum(times):.1f} s (first {times[0]:.2f} s, "
          f"mean of the rest {sum(times[1:]) / max(1, made - 1):.2f} s)")
    metrics = requests.get(f"{base}/metrics").text
    for line in metrics.splitlines():
        if "factor_type" in line and not line.startswith("#"):
            print("  metrics:", line)
    p.send_signal(signal.SIGKILL); p.wait()
    p, health = start(binary, state, port)
    print(f"restart: first /health after {health:.2f} s")
    t0 = time.monotonic()
    while True:
        listed = requests.get(f"{base}/v1/sessions", timeout=10).json()["sessions"]
        stats = [requests.get(f"{base}/v1/sessions/{s['session']}", timeout=10).json()
                 for s in listed]
        if len(stats) == made and not any(st["recovering"] for st in stats):
            break
        time.sleep(0.05)
    print(f"restart: {made} sessions recovered {time.monotonic() - t0 + health:.2f} s after the "
          f"start, RSS {rss_mb(p.pid):.0f} MB; factors {[st['num_factors'] for st in stats]}")
    p.send_signal(signal.SIGKILL); p.wait()
    shutil.rmtree(state, ignore_errors=True)


main()
