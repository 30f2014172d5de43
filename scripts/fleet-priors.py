#!/usr/bin/env python3
r"""Localize the held-out frames of a drive in a region built from the drive, from priors 5 m / 30°
off, against a running server, and re-send each answer as the next prior (re-centring the
region's crop on it), to see whether the answer walks off the prior (docs/server.md, "Known
limit"). The cases are `tests/fleet_maps.rs`'s: odd frames, the truth moved 5 m in direction
47°·frame and turned ±30° (+ when frame % 4 == 1).

    cmr-agent synth --out D --world classic --look classic --style test --frames 84 --seed 7100 --quiet
    cmr-agent map build --sequence D/00 --out map.ply --step 2
    cmr-agent serve --port 8090 --maps M --max-map-bytes 400000000 --request-timeout-ms 60000 &
    curl -X PUT --data-binary @map.ply localhost:8090/v1/maps/drive
    python3 scripts/fleet-priors.py --server http://localhost:8090 --id drive --sequence D/00 \
        --hypotheses 1 --rounds 3

Prints per frame the position / rotation error after each round, and per round RR (5 m / 10°),
the answers within 1 m, those turned by more than 150° and the HTTP errors (counted as failures).
Python standard library only (the sequence helpers of scripts/track-http.py).
"""

import argparse
import base64
import importlib.util
import json
import math
import os
import urllib.request

spec = importlib.util.spec_from_file_location("track_http", os.path.join(os.path.dirname(__file__), "track-http.py"))
th = importlib.util.module_from_spec(spec)
spec.loader.exec_module(th)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="http://localhost:8080")
    ap.add_argument("--id", required=True)
    ap.add_argument("--sequence", required=True)
    ap.add_argument("--hypotheses", type=int, default=4, help="starts of the first round (later rounds: 1)")
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    seq = th.read_sequence(args.sequence)
    rounds = [[] for _ in range(args.rounds)]
    for index, path in seq["images"]:
        if index % 2 != 1:
            continue
        truth = th.truth_camera_from_map(seq, index)
        prior = th.perturbed(truth, 5.0, math.radians(index * 47.0), math.radians(30.0 if index % 4 == 1 else -30.0))
        image = base64.b64encode(open(path, "rb").read()).decode()
        line = f"frame {index:3d}"
        for r in range(args.rounds):
            try:
                pose, _, _ = th.localize(args.server, args.id, image, seq["intrinsics"], prior, args.hypotheses if r == 0 else 1, 10)
            except SystemExit as e:  # an HTTP error (track-http's localize exits): a failure of this frame
                line += f" | round {r + 1}: {e}"
                rounds[r:] = [errors + [(math.inf, math.inf)] for errors in rounds[r:]]
                break
            prior = pose
            m = math.dist(th.centre(pose), th.centre(truth))
            deg = th.angle_deg(th.mul(th.inv(pose), truth))
            rounds[r].append((m, deg))
            line += f" | round {r + 1}: {m:5.2f} m {deg:6.1f} deg"
        print(line, flush=True)
    for r, errors in enumerate(rounds):
        ok = [e for e in errors if e[0] < 5.0 and e[1] < 10.0]
        mean = sum(e[0] for e in ok) / max(len(ok), 1)
        print(f"round {r + 1}: RR {len(ok)}/{len(errors)} (5 m / 10 deg), mean position error {mean:.2f} m over the registered, "
              f"{sum(e[0] < 1.0 and e[1] < 10.0 for e in errors)} within 1 m, {sum(150 < e[1] < math.inf for e in errors)} turned > 150 deg, "
              f"{sum(e[0] == math.inf for e in errors)} HTTP errors")


if __name__ == "__main__":
    main()
