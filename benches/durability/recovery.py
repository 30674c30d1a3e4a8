"""Recovery time of a big durable session: stream a g2o 2D graph into `factord serve` pose by pose
(every-batch solving, fsync always), kill -9 the server, restart it on the same state directory
and time how long until the session takes writes again and until its re-solve has finished.

    python3 benches/durability/recovery.py FACTORD_BINARY GRAPH.g2o [--snapshot-every N]
"""
import argparse, json, os, shutil, signal, subprocess, tempfile, time, urllib.request


def call(url, body=None, method=None):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method or ("POST" if data else "GET"),
                                 headers={"content-type": "application/json"})
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.load(r)


def batches(path):
    vertices, edges = {}, []
    for line in open(path):
        t = line.split()
        if t and t[0] == "VERTEX_SE2":
            vertices[int(t[1])] = [float(x) for x in t[2:5]]
        elif t and t[0] == "EDGE_SE2":
            a, b = int(t[1]), int(t[2])
            edges.append((max(a, b), {"type": "between_se2", "keys": [a, b],
                                      "measurement": [float(x) for x in t[3:6]],
                                      "information": [float(x) for x in t[6:12]]}))
    by_key = {}
    for k, f in edges:
        by_key.setdefault(k, []).append(f)
    for k in sorted(vertices):
        yield {"variables": [{"key": k, "kind": "se2", "value": vertices[k]}], "factors": by_key.get(k, [])}


def start(binary, state, config):
    try:
        os.remove(os.path.join(state, "server.json"))
    except FileNotFoundError:
        pass
    p = subprocess.Popen([binary, "serve", "--listen", "127.0.0.1:0", "--no-zenoh", "--state-dir", state,
                          "--config", config, "--log", "warn"], stderr=subprocess.DEVNULL)
    t0 = time.time()
    while not os.path.exists(os.path.join(state, "server.json")):
        time.sleep(0.005)
    while True:
        try:
            return p, "http://" + json.load(open(os.path.join(state, "server.json")))["http"], t0
        except ValueError:
            time.sleep(0.005)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binary")
    ap.add_argument("graph")
    ap.add_argument("--snapshot-every", type=int, default=2000)
    a = ap.parse_args()
    work = tempfile.mkdtemp()
    state, config = os.path.join(work, "state"), os.path.join(work, "config.json")
    json.dump({"journal": {"snapshot_every": a.snapshot_every}}, open(config, "w"))
    p, url, _ = start(a.binary, state, config)
    call(url + "/v1/sessions", {"session": "big", "kind": "pose_graph_2d"})
    t = time.time()
    n = 0
    for b in batches(a.graph):
        call(url + "/v1/sessions/big/batches", b)
        n += 1
    stream = time.time() - t
    before = call(url + "/v1/sessions/big")
    p.send_signal(signal.SIGKILL)
    p.wait()
    p, url, t0 = start(a.binary, state, config)
    while True:
        s = call(url + "/v1/sessions/big")
        if not s["recovering"]:
            writable = time.time() - t0
            break
        time.sleep(0.002)
    while True:
        s = call(url + "/v1/sessions/big")
        if not s["solving"] and s["solved_sequence"] == s["sequence"] and s["solves"] >= 1:
            solved = time.time() - t0
            break
        time.sleep(0.005)
    p.send_signal(signal.SIGTERM)
    p.wait()
    shutil.rmtree(work)
    print(json.dumps({"graph": a.graph, "batches": n, "stream_seconds": round(stream, 2),
                      "acknowledged_sequence": before["sequence"], "recovered_sequence": s["sequence"],
                      "variables": s["num_variables"], "factors": s["num_factors"],
                      "restart_to_writable_seconds": round(writable, 3),
                      "restart_to_resolved_seconds": round(solved, 3),
                      "chi2_before": before["chi2"], "chi2_after": s["chi2"]}))


if __name__ == "__main__":
    main()
