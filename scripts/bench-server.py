#!/usr/bin/env python3
"""Load benchmark of the localization server over loopback HTTP (stdlib only; not a test).

Prints: p50/p95 latency of one localize with a warm map (sequential), per-stage medians from the
response's timings_ms, the time to register a 40,960-point map (PUT, client wall time and server
phases), and requests/s at concurrency 8 (bounded in count and time), plus batching counters.

    python3 scripts/bench-server.py --spawn                      # starts ./target/release/cmr-agent
    python3 scripts/bench-server.py --url http://127.0.0.1:8080  # against a running server
"""

import argparse
import http.client
import json
import os
import random
import signal
import statistics
import struct
import subprocess
import sys
import threading
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor

STAGES = ["queue", "decode", "image_encoder", "frustum_head", "agent_steps", "agent_state_build", "total"]


class Client:
    """One keep-alive connection (one per thread)."""

    def __init__(self, url, token=None):
        u = urllib.parse.urlparse(url)
        self.host, self.port = u.hostname, u.port or 80
        self.token = token
        self.conn = None

    def request(self, method, path, body=None, content_type="application/json"):
        headers = {"content-type": content_type}
        if self.token:
            headers["authorization"] = f"Bearer {self.token}"
        for attempt in range(2):
            try:
                if self.conn is None:
                    self.conn = http.client.HTTPConnection(self.host, self.port, timeout=120)
                self.conn.request(method, path, body=body, headers=headers)
                r = self.conn.getresponse()
                data = r.read()
                return r.status, data
            except (http.client.HTTPException, ConnectionError):
                self.conn = None
                if attempt:
                    raise


def pct(values, q):
    if not values:
        return float("nan")
    s = sorted(values)
    k = max(0, min(len(s) - 1, round(q / 100 * (len(s) - 1))))
    return s[k]


def localize_once(client, path, body):
    t = time.perf_counter()
    status, data = client.request("POST", path, body)
    wall = (time.perf_counter() - t) * 1000
    timings = json.loads(data).get("timings_ms") if status == 200 else None
    return status, wall, timings


def wait_ready(url, timeout_s=120):
    c = Client(url)
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        try:
            if c.request("GET", "/ready")[0] == 200:
                return
        except OSError:
            c.conn = None
        time.sleep(0.1)
    sys.exit("server did not become ready")


def metric_sum(text, name):
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name) and not line.startswith("#"):
            head = line.split(" ")[0]
            if head == name or head.startswith(name + "{"):
                total += float(line.rsplit(" ", 1)[1])
    return total


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--map", default="demo")
    ap.add_argument("--request", default="examples/localize-demo.json")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--sequential", type=int, default=30, help="sequential requests for p50/p95")
    ap.add_argument("--concurrency", type=int, default=8)
    ap.add_argument("--concurrent-requests", type=int, default=64)
    ap.add_argument("--time-limit-s", type=float, default=60.0, help="bound of the concurrent phase")
    ap.add_argument("--register-points", type=int, default=40960)
    ap.add_argument("--register-repeats", type=int, default=3)
    ap.add_argument("--token", default=os.environ.get("CMR_ADMIN_TOKEN"))
    ap.add_argument("--spawn", action="store_true", help="start ./target/release/cmr-agent serve on a free port")
    ap.add_argument("--serve-args", default="", help="extra flags for the spawned server")
    args = ap.parse_args()

    server = None
    if args.spawn:
        port = 18000 + random.randrange(1000)
        args.url = f"http://127.0.0.1:{port}"
        cmd = ["./target/release/cmr-agent", "serve", "--host", "127.0.0.1", "--port", str(port)] + args.serve_args.split()
        server = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
    try:
        wait_ready(args.url)
        run(args)
    finally:
        if server is not None:
            server.send_signal(signal.SIGTERM)
            server.wait(timeout=30)


def run(args):
    with open(args.request, "rb") as f:
        body = f.read()
    path = f"/v1/maps/{args.map}/localize"
    c = Client(args.url, args.token)
    info = json.loads(c.request("GET", "/v1/info")[1])
    print(f"server {args.url}: {info['name']} {info['version']}, workers {info['workers']}, "
          f"max_batch {info['limits']['max_batch']}, model {info['manifest']['provenance'].get('created', '?')}")

    for _ in range(args.warmup):
        status, _, _ = localize_once(c, path, body)
        if status != 200:
            sys.exit(f"warm-up localize failed with HTTP {status}")

    walls, stages = [], {s: [] for s in STAGES}
    for _ in range(args.sequential):
        status, wall, timings = localize_once(c, path, body)
        assert status == 200, status
        walls.append(wall)
        for s in STAGES:
            stages[s].append(timings[s])
    print(f"\nlocalize, warm map, sequential x{len(walls)} (client wall ms): "
          f"p50 {pct(walls, 50):.1f}  p95 {pct(walls, 95):.1f}  mean {statistics.mean(walls):.1f}")
    print("  server stages, median ms: " + "  ".join(f"{s} {statistics.median(stages[s]):.2f}" for s in STAGES))

    rng = random.Random(0)
    cloud = b"".join(struct.pack("<4f", rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-2, 4), 0.0)
                     for _ in range(args.register_points))
    reg_walls, reg_enc = [], []
    for _ in range(args.register_repeats):
        t = time.perf_counter()
        status, data = c.request("PUT", "/v1/maps/bench-register?format=kitti_bin", cloud, "application/octet-stream")
        reg_walls.append((time.perf_counter() - t) * 1000)
        if status not in (200, 201):
            print(f"register failed: HTTP {status} {data[:200]!r}")
            break
        reg_enc.append(json.loads(data)["timings_ms"])
    c.request("DELETE", "/v1/maps/bench-register")
    if reg_enc:
        med = {k: statistics.median(r[k] for r in reg_enc) for k in reg_enc[0]}
        print(f"\nregister a {args.register_points}-point map (PUT, KITTI .bin, x{len(reg_walls)}): "
              f"client wall median {statistics.median(reg_walls):.1f} ms; server median ms: "
              + "  ".join(f"{k} {v:.1f}" for k, v in med.items()))

    before = c.request("GET", "/metrics")[1].decode()
    results = []
    lock = threading.Lock()
    deadline = time.time() + args.time_limit_s
    counter = iter(range(args.concurrent_requests))

    def worker():
        wc = Client(args.url, args.token)
        while time.time() < deadline:
            with lock:
                if next(counter, None) is None:
                    return
            status, wall, _ = localize_once(wc, path, body)
            with lock:
                results.append((status, wall))

    t0 = time.perf_counter()
    with ThreadPoolExecutor(args.concurrency) as pool:
        for f in [pool.submit(worker) for _ in range(args.concurrency)]:
            f.result()
    elapsed = time.perf_counter() - t0
    after = c.request("GET", "/metrics")[1].decode()
    ok = [w for s, w in results if s == 200]
    codes = {}
    for s, _ in results:
        codes[s] = codes.get(s, 0) + 1
    print(f"\nconcurrency {args.concurrency}: {len(results)} requests in {elapsed:.2f} s -> "
          f"{len(ok) / elapsed:.2f} successful requests/s; statuses {codes}; "
          f"latency p50 {pct(ok, 50):.1f} ms p95 {pct(ok, 95):.1f} ms")
    calls = metric_sum(after, "cmr_batch_size_count") - metric_sum(before, "cmr_batch_size_count")
    stepped = metric_sum(after, "cmr_batch_size_sum") - metric_sum(before, "cmr_batch_size_sum")
    if calls:
        print(f"  batched policy calls {calls:.0f}, mean batch {stepped / calls:.2f}")


if __name__ == "__main__":
    main()
