#!/usr/bin/env python3
"""Peak memory and time of the server on images that are cheap to send and costly to decode.

Spawns `BINARY serve` (default ./target/release/cmr-agent) on a free loopback port with the demo
map, sends each case (stdlib client, a bounded number of requests), and prints per case: the
HTTP status, the error_type, the client wall time and the server's peak RSS growth (VmHWM from
/proc, in MiB, over the RSS after warm-up). Not a test: a probe whose figures go in
docs/server.md. Cases:
  png-8000x8000   an 8000x8000 PNG of zeros (about 190 KB)
  png-8000x8000x6 six of them at once
  png-1x8192      a 1x8192 PNG (about 1 KB)
  png-4000x4000   a 16 MP PNG of zeros, just inside today's default budget (and six at once)

    python3 scripts/probe-decode.py [--binary PATH]
"""

import argparse
import base64
import http.client
import json
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib


def png(width, height):
    """A grey-scale-free RGB PNG of zeros, written row by row so it never holds the raw image."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    comp = zlib.compressobj(9)
    row = b"\x00" + b"\x00" * (3 * width)
    parts = [comp.compress(row) for _ in range(height)]
    idat = b"".join(parts) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def rss_kib(pid, field):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field):
                return int(line.split()[1])
    return 0


def post(port, body, timeout=120):
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    t = time.perf_counter()
    try:
        c.request("POST", "/v1/maps/demo/localize", body=body, headers={"content-type": "application/json"})
        r = c.getresponse()
        data = r.read()
        status = r.status
    except Exception as e:  # the server may die of memory
        return None, type(e).__name__, (time.perf_counter() - t) * 1000
    wall = (time.perf_counter() - t) * 1000
    try:
        kind = json.loads(data).get("error_type", "ok")
    except ValueError:
        kind = "?"
    return status, kind, wall


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", default="./target/release/cmr-agent")
    args = ap.parse_args()
    intr = {"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}
    body = lambda img: json.dumps({"image": base64.b64encode(img).decode(), "intrinsics": intr, "max_iterations": 1}).encode()
    big = body(png(8000, 8000))
    ok = body(png(4000, 4000))
    cases = [("png-8000x8000", big, 1), ("png-8000x8000x6", big, 6), ("png-1x8192", body(png(1, 8192)), 1),
             ("png-4000x4000", ok, 1), ("png-4000x4000x6", ok, 6)]
    for name, payload, parallel in cases:
        maps = tempfile.mkdtemp()
        shutil.copy("maps/demo.bin", maps)
        shutil.copy("maps/demo.json", maps)
        port = 18000 + random.randrange(1000)
        server = subprocess.Popen([args.binary, "serve", "--host", "127.0.0.1", "--port", str(port), "--maps", maps], stderr=subprocess.DEVNULL)
        try:
            deadline = time.time() + 120
            while time.time() < deadline:
                try:
                    c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                    c.request("GET", "/ready")
                    if c.getresponse().status == 200:
                        break
                except OSError:
                    pass
                time.sleep(0.2)
            base = rss_kib(server.pid, "VmRSS")
            results = []
            threads = [threading.Thread(target=lambda: results.append(post(port, payload))) for _ in range(parallel)]
            t = time.perf_counter()
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            wall = (time.perf_counter() - t) * 1000
            alive = server.poll() is None
            peak = rss_kib(server.pid, "VmHWM") if alive else float("nan")
            statuses = sorted({f"{s} {k}" for s, k, _ in results})
            print(f"{name:18s} {', '.join(statuses):40s} wall {wall:8.0f} ms  peak RSS +{(peak - base) / 1024:7.1f} MiB"
                  f"{'' if alive else '  (server died)'}")
        finally:
            if server.poll() is None:
                server.send_signal(signal.SIGTERM)
                server.wait(timeout=30)
            shutil.rmtree(maps, ignore_errors=True)


if __name__ == "__main__":
    main()
