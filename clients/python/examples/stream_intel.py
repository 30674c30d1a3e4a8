"""Streams intel pose by pose from numpy arrays; reads the optimum back as an (N, 3) array.
python stream_intel.py [file.g2o] [url]   (a server with tokens: export FACTORD_TOKEN=...)"""
import sys
import numpy as np
from factord_client import Batch, HttpClient
rows = [r.split() for r in open((sys.argv[1:] or ["../shared/data/2d/sesync/intel.g2o"])[0])]
V = np.array([r[1:5] for r in rows if r[0] == "VERTEX_SE2"], float)  # id, x, y, θ
E = np.array([r[1:12] for r in rows if r[0] == "EDGE_SE2"], float)  # i, j, dx, dy, dθ, information
with HttpClient(*sys.argv[2:3]) as c:  # default http://127.0.0.1:8080
    s = c.create_session("pose_graph_2d")["session"]
    for k, pose in zip(V[:, 0].astype(int), V[:, 1:]):  # pose k and the edges that reach it
        e = E[E[:, :2].max(axis=1) == k]
        c.apply_batch(s, Batch().poses([k], [pose]).between_many(e[:, :2], e[:, 2:5], e[:, 5:]))
    chi2, (keys, poses) = c.optimize(s, wait=True)["stats"]["chi2"], c.estimate_array(s)
    print(f"session {s}: poses {poses.shape}, chi2 {chi2:.6f}")  # keys (N,), poses (N, 3): x y θ
