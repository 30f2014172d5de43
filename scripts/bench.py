#!/usr/bin/env python3
"""Benchmark of the localization server on loopback (`make bench`); prints figures, writes a JSON
record; not a test (no assertions on speed).

Starts `BINARY serve` on a free port with a copy of the demo map and measures, for each of two
requests (the default search):
  - demo: `examples/localize-demo.json` on the demo map;
  - real-size: a full-size KITTI frame (the PNG of `../shared/real-dev/sequences/01`, 1242x375,
    ~0.9 MB of base64) in its own scan uploaded as a region (`PUT ?format=kitti_bin`), the prior the
    truth turned 20 deg about the vertical and moved 1.9 m along the ground; where real-dev is
    absent, a full-size synthetic KITTI-rig frame and its scan (`cmr-agent synth --rig kitti`);
the phases:
  1. sequential: p50 / p99 client latency of one localize at a time (oha -c 1), the server's
     per-phase medians (response `timings_ms`), and the server's CPU time per request;
  2. concurrency 16 for `--seconds` (oha -c 16): requests/s, p50 / p99, statuses, CPU per request,
     policy rows per request (from /metrics) and mean batch;
  3. registration of a 40,960-point map (PUT, x3; once per run);
  4. FLOPs per request from the manifest (`graphs.*.flops`: image encoder (four passes with the
     judge's views, `limits.judge_zoom` > 0) + frustum head on the M
     state points + rows x (agent + the server-side correlation, `correlation_flops`)) and the
     share of the FLOP floor reached at c16 (`--peak-gflops`, the machine's fp32 matmul rate on
     all cores);
  5. with `--storm`: a second server with `--queue-capacity 4` under 48 closed-loop clients:
     admitted (200) requests/s against its capacity measured in the same run at 4 clients.

    python3 scripts/bench.py [--binary PATH] [--models DIR] [--serve-args "..."] [--seconds 30] [--storm] [--out FILE]
    python3 scripts/bench.py --baseline OLD_BINARY [--baseline-models DIR] [--baseline-serve-args "..."] [--rounds 2] ...   # A/B, ratios

On a machine whose speed drifts (this one's did by a third within an hour), compare builds with
`--baseline`: the two servers run alternately and the ratios of each figure are reported.
oha (a Rust HTTP load generator) comes from scripts/install-oha.sh (into .tools/bin).
"""

import argparse
import base64
import http.client
import importlib.util
import json
import math
import os
import random
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import time

OHA = os.path.join(os.path.dirname(__file__), "..", ".tools", "bin", "oha")
# The KITTI sequence helpers (calibration, truth, a prior moved on the ground) of track-http.py.
_spec = importlib.util.spec_from_file_location("track_http", os.path.join(os.path.dirname(__file__), "track-http.py"))
TRACK = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(TRACK)
STAGES = ["queue", "decode", "image_encoder", "frustum_head", "agent_steps", "agent_state_build", "agent_polish", "total"]
TICK = os.sysconf("SC_CLK_TCK")


class Server:
    """A spawned `serve` on a free loopback port with its own copy of the demo map."""

    def __init__(self, binary, extra):
        self.maps = tempfile.mkdtemp(prefix="cmr-bench-")
        for f in ("demo.bin", "demo.json"):
            shutil.copy(os.path.join("maps", f), self.maps)
        self.port = 20000 + random.randrange(20000)
        cmd = [binary, "serve", "--host", "127.0.0.1", "--port", str(self.port), "--maps", self.maps] + extra
        self.proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
        self.url = f"http://127.0.0.1:{self.port}"
        deadline = time.time() + 180
        while time.time() < deadline:
            try:
                if self.request("GET", "/ready")[0] == 200:
                    return
            except OSError:
                pass
            time.sleep(0.2)
        self.stop()
        sys.exit("server did not become ready")

    def request(self, method, path, body=None, ctype="application/json"):
        c = http.client.HTTPConnection("127.0.0.1", self.port, timeout=120)
        c.request(method, path, body=body, headers={"content-type": ctype})
        r = c.getresponse()
        return r.status, r.read()

    def cpu_s(self):
        with open(f"/proc/{self.proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / TICK

    def metric(self, name):
        text = self.request("GET", "/metrics")[1].decode()
        total = 0.0
        for line in text.splitlines():
            head = line.split(" ")[0]
            if head == name or head.startswith(name + "{"):
                total += float(line.rsplit(" ", 1)[1])
        return total

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=60)
        shutil.rmtree(self.maps, ignore_errors=True)


def oha(url, request, *args):
    out = subprocess.run([OHA, "--no-tui", "--output-format", "json", "-m", "POST", "-T", "application/json",
                          "-D", request, *args, url], capture_output=True, text=True, check=True).stdout
    d = json.loads(out)
    lat = d["latencyPercentiles"]
    ms = lambda v: None if v is None else v * 1000
    return {"requests_per_s": d["summary"]["requestsPerSec"], "p50_ms": ms(lat["p50"]), "p99_ms": ms(lat["p99"]),
            "statuses": d["statusCodeDistribution"], "errors": d["errorDistribution"], "seconds": d["summary"]["total"]}


def load_phase(server, request, connections, seconds, map_id="demo"):
    path = server.url + f"/v1/maps/{map_id}/localize"
    cpu0, rows0, calls0 = server.cpu_s(), server.metric("cmr_batch_size_sum"), server.metric("cmr_batch_size_count")
    views0 = server.metric("cmr_judge_views_read_total")
    r = oha(path, request, "-c", str(connections), "-z", f"{seconds}s")
    ok = r["statuses"].get("200", 0)
    rows, calls = server.metric("cmr_batch_size_sum") - rows0, server.metric("cmr_batch_size_count") - calls0
    r["ok_per_s"] = ok / r["seconds"]
    r["cpu_ms_per_request"] = (server.cpu_s() - cpu0) * 1000 / max(ok, 1)
    r["policy_rows_per_request"] = rows / max(ok, 1)
    # Requests whose judge read its three views (`--judge-gate`), per request answered.
    r["views_read_per_request"] = (server.metric("cmr_judge_views_read_total") - views0) / max(ok, 1)
    r["mean_batch_rows"] = rows / max(calls, 1)
    return r


def correlation_flops(manifest: dict) -> int:
    """FLOPs per policy row that the server spends on the correlation-form state (manifest
    `state_2d`), counted as if every cell were occupied (an upper bound): one D-long dot product
    per shift and cell. 0 for the features form, whose agent graph counts its own correlation."""
    spec = manifest.get("state_2d", {"form": "features"})
    if spec.get("form") != "correlation":
        return 0
    f = manifest["features"]
    shifts = len(spec["row_shifts"]) + len(spec["column_shifts"])
    return 2 * shifts * f["dim"] * f["grid_height"] * f["grid_width"]


def real_size_workload(binary, sequence, workdir):
    """The real-size request: frame 0 of the KITTI-layout `sequence` (its image_2 PNG, its scan as
    the region, the truth and the prior from scripts/track-http.py's sequence helpers) or, when
    `sequence` is missing, a full-size synthetic KITTI-rig frame written into `workdir`. Returns
    (description, scan bytes, body file)."""
    if not os.path.isdir(sequence):
        subprocess.run([binary, "synth", "--out", os.path.join(workdir, "synth"), "--rig", "kitti", "--sequences", "1",
                        "--frames", "1", "--seed", "4242", "--quiet"], check=True)
        sequence = os.path.join(workdir, "synth", "00")
    seq = TRACK.read_sequence(sequence)
    index, image = seq["images"][0]
    body = {
        "image": base64.b64encode(open(image, "rb").read()).decode(),
        "intrinsics": seq["intrinsics"],
        "prior_camera_from_map": TRACK.perturbed(TRACK.truth_camera_from_map(seq, index), 1.9, 0.7, math.radians(20.0)),
    }
    path = os.path.join(workdir, "real-size.json")
    with open(path, "w") as f:
        json.dump(body, f)
    scan_bytes = open(os.path.join(sequence, "velodyne", f"{index:06d}.bin"), "rb").read()
    return f"{sequence} ({len(scan_bytes) // 16:,} points, {len(body['image']) / 1e6:.2f} MB of base64)", scan_bytes, path


def measure_request(server, name, map_id, request, flops, manifest, args):
    """Sequential and c16 phases of one request against `server`: prints, returns the record."""
    path = f"/v1/maps/{map_id}/localize"
    body = open(request, "rb").read()
    for _ in range(3):
        status, data = server.request("POST", path, body)
        assert status == 200, data[:300]
    stages = {s: [] for s in STAGES}
    cpu0 = server.cpu_s()
    for _ in range(args.sequential):
        status, data = server.request("POST", path, body)
        assert status == 200, data[:200]
        t = json.loads(data)["timings_ms"]
        for s in STAGES:
            stages[s].append(t[s])
    seq_cpu = (server.cpu_s() - cpu0) * 1000 / args.sequential
    seq = oha(server.url + path, request, "-c", "1", "-n", str(args.sequential))
    seq["server_phase_median_ms"] = {s: statistics.median(v) for s, v in stages.items()}
    seq["cpu_ms_per_request"] = seq_cpu
    print(f"[{name}] sequential x{args.sequential}: p50 {seq['p50_ms']:.1f} ms, p99 {seq['p99_ms']:.1f} ms; "
          f"server CPU {seq_cpu:.1f} ms per request")
    print(f"[{name}]   server phases, median ms: " + "  ".join(f"{s} {v:.1f}" for s, v in seq["server_phase_median_ms"].items()))

    c16 = load_phase(server, request, 16, args.seconds, map_id)
    print(f"[{name}] c16, {args.seconds} s: {c16['ok_per_s']:.2f} localizations/s, p50 {c16['p50_ms']:.0f} ms, "
          f"p99 {c16['p99_ms']:.0f} ms, statuses {c16['statuses']}; CPU {c16['cpu_ms_per_request']:.1f} ms "
          f"per request; {c16['policy_rows_per_request']:.1f} policy rows per request, mean batch "
          f"{c16['mean_batch_rows']:.1f}")
    record = {"sequential": seq, "c16": c16}
    if all(flops.values()):
        # The manifest counts the frustum head at N points; the server runs it on the M state
        # points, and its cost is per point (the image context MLP is ~0.3 MFLOP).
        points = manifest["points"]
        frustum = flops["frustum_head"] * points["num_state_points"] / points["num_points"]
        # The judge's views (`--judge-zoom`): three more image encoder passes for each request
        # whose judge read them (`--judge-gate`; the server's counter).
        views = 3 * c16["views_read_per_request"]
        per_request = (1 + views) * flops["image_encoder"] + frustum + c16["policy_rows_per_request"] * (flops["agent"] + correlation_flops(manifest))
        ceiling = args.peak_gflops * 1e9 / per_request
        record["flops"] = {"per_request_gflop": per_request / 1e9, "ceiling_requests_per_s": ceiling,
                           "share_of_floor": c16["ok_per_s"] / ceiling, "peak_gflops": args.peak_gflops}
        print(f"[{name}] FLOPs: {per_request / 1e9:.2f} GFLOP per request ({c16['policy_rows_per_request']:.1f} rows); "
              f"at {args.peak_gflops:.0f} GFLOP/s the ceiling is {ceiling:.1f} requests/s; c16 reaches "
              f"{100 * c16['ok_per_s'] / ceiling:.0f} % of it")
    return record


def measure(binary, models, args, serve_args=None):
    """One run of every phase against `binary` serving `models` with `serve_args` (default
    `--serve-args`): prints the figures, returns the record."""
    serve_args = args.serve_args if serve_args is None else serve_args
    record = {"binary": binary, "serve_args": serve_args, "request": args.request,
              "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "load_average_before": os.getloadavg()}
    manifest = json.load(open(os.path.join(models, "manifest.json")))
    record["models"] = models
    flops = {k: v.get("flops") for k, v in manifest["graphs"].items()}

    server = Server(binary, serve_args.split() + ["--models", models])
    workdir = tempfile.mkdtemp(prefix="cmr-bench-real-size-")
    try:
        record["demo"] = measure_request(server, "demo", "demo", args.request, flops, manifest, args)
        # kept at the top level too, as earlier records had them
        record["sequential"], record["c16"] = record["demo"]["sequential"], record["demo"]["c16"]

        if not args.no_real_size:
            described, scan, request = real_size_workload(binary, args.real_size_sequence, workdir)
            status, data = server.request("PUT", "/v1/maps/bench-real-size?format=kitti_bin", scan, "application/octet-stream")
            assert status in (200, 201), data[:300]
            print(f"[real-size] {described}")
            record["real_size"] = measure_request(server, "real-size", "bench-real-size", request, flops, manifest, args)
            record["real_size"]["source"] = described

        rng = random.Random(0)
        cloud = b"".join(struct.pack("<4f", rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-2, 4), 0.0)
                         for _ in range(40960))
        walls = []
        for _ in range(3):
            t = time.perf_counter()
            status, _ = server.request("PUT", "/v1/maps/bench-register?format=kitti_bin", cloud, "application/octet-stream")
            walls.append((time.perf_counter() - t) * 1000)
            assert status in (200, 201), status
        record["register_40960_points_ms"] = statistics.median(walls)
        print(f"register a 40,960-point map: median {record['register_40960_points_ms']:.1f} ms (x3)")
    finally:
        server.stop()
        shutil.rmtree(workdir, ignore_errors=True)

    if args.storm:
        storm_server = Server(binary, serve_args.split() + ["--models", models, "--queue-capacity", "4"])
        try:
            capacity = load_phase(storm_server, args.request, 4, 20)
            storm = load_phase(storm_server, args.request, 48, 20)
            record["storm"] = {"capacity_4_clients": capacity, "storm_48_clients": storm,
                               "admitted_share": storm["ok_per_s"] / max(capacity["ok_per_s"], 1e-9)}
            print(f"storm (queue 4): capacity {capacity['ok_per_s']:.2f}/s at 4 clients; 48 clients: "
                  f"{storm['ok_per_s']:.2f}/s admitted ({100 * record['storm']['admitted_share']:.0f} %), "
                  f"statuses {storm['statuses']}")
        finally:
            storm_server.stop()

    record["load_average_after"] = os.getloadavg()
    return record


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", default="./target/release/cmr-agent")
    ap.add_argument("--models", default="models", help="model directory (the server's --models; FLOPs are read from its manifest)")
    ap.add_argument("--serve-args", default="", help="extra flags for the server")
    ap.add_argument("--request", default="examples/localize-demo.json")
    ap.add_argument("--seconds", type=int, default=30, help="length of the c16 phase")
    ap.add_argument("--sequential", type=int, default=40)
    ap.add_argument("--peak-gflops", type=float, default=183.0,
                    help="fp32 matmul GFLOP/s of this machine on all cores (183: 2-core dev machine, issue 15)")
    ap.add_argument("--storm", action="store_true", help="also measure admitted throughput under overload")
    ap.add_argument("--baseline", metavar="BINARY", help="also run this binary, alternating with --binary, and print ratios")
    ap.add_argument("--baseline-models", metavar="DIR", help="the baseline's model directory (default: --models)")
    ap.add_argument("--baseline-serve-args", metavar="ARGS", help="the baseline server's extra flags (default: --serve-args)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds with --baseline")
    ap.add_argument("--real-size-sequence", default=os.path.join("..", "shared", "real-dev", "sequences", "01"),
                    help="KITTI-layout sequence whose frame 0 makes the real-size request (synthetic when missing)")
    ap.add_argument("--no-real-size", action="store_true", help="measure the demo request only")
    ap.add_argument("--out", default="bench.json")
    args = ap.parse_args()
    if not os.path.exists(OHA):
        sys.exit("oha not found: run scripts/install-oha.sh")
    if not args.baseline:
        record = measure(args.binary, args.models, args)
    else:
        # Alternate the two, so that a machine whose speed drifts affects both alike; report the
        # median over rounds of each figure's ratio (candidate / baseline).
        runs = {"baseline": [], "candidate": []}
        for r in range(args.rounds):
            baseline_serve_args = args.serve_args if args.baseline_serve_args is None else args.baseline_serve_args
            for name, binary, models, serve_args in (
                    ("baseline", args.baseline, args.baseline_models or args.models, baseline_serve_args),
                    ("candidate", args.binary, args.models, args.serve_args)):
                print(f"== round {r + 1}/{args.rounds}: {name} ({binary}, {models}, {serve_args!r})")
                runs[name].append(measure(binary, models, args, serve_args))
        figures = {
            "c16 requests/s": lambda x: x["c16"]["ok_per_s"],
            "c16 CPU ms per request": lambda x: x["c16"]["cpu_ms_per_request"],
            "sequential p50 ms": lambda x: x["sequential"]["p50_ms"],
            "sequential CPU ms per request": lambda x: x["sequential"]["cpu_ms_per_request"],
            **({} if args.no_real_size else {
                "real-size c16 requests/s": lambda x: x["real_size"]["c16"]["ok_per_s"],
                "real-size sequential p50 ms": lambda x: x["real_size"]["sequential"]["p50_ms"],
                "real-size sequential CPU ms per request": lambda x: x["real_size"]["sequential"]["cpu_ms_per_request"],
            }),
            "register 40,960 points ms": lambda x: x["register_40960_points_ms"],
        }
        ratios = {k: statistics.median(f(c) / f(b) for b, c in zip(runs["baseline"], runs["candidate"])) for k, f in figures.items()}
        record = {"runs": runs, "ratios_candidate_over_baseline": ratios}
        print(f"candidate / baseline, median over {args.rounds} alternating rounds:")
        for k, v in ratios.items():
            print(f"  {k}: {v:.3f}")
    with open(args.out, "w") as f:
        json.dump(record, f, indent=2)
    if "load_average_before" in record:
        print(f"record: {args.out} (load average before {record['load_average_before'][0]:.2f}, "
              f"after {record['load_average_after'][0]:.2f})")
    else:
        print(f"record: {args.out}")


if __name__ == "__main__":
    main()
