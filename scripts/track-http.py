#!/usr/bin/env python3
"""Follow a KITTI-layout drive against a running cmr-agent server (Python standard library only).

The same loop as `cmr-agent track` (src/track/mod.rs), over HTTP: the first frame is localized
with the full search from a coarse prior (the truth moved --prior-noise-m in the ground plane and
turned --prior-noise-deg about the vertical), every later frame from the previous estimate moved
by a constant-velocity prediction (the last measured motion per frame: steps from a dead-reckoned
frame, or into a fallback after a tracked frame, are corrections, not motion) with a small search (--tracked-hypotheses starts,
--tracked-iterations steps) from the prediction and from it moved along its optical axis by
+-k * --tracked-axis-step-m, k = 1..--tracked-axis-starts, in one request (its `axis_starts`:
the server keeps the answer with the highest alignment score, the prediction's own with
--tracked-axis-margin added). That answer is kept when the server says it is
`localized` (the model set's calibrated verdict) and its confidence score is at least
--fallback-below; otherwise the frame is redone with the full search (the server's defaults) from
the prior that small search's answer started from, and when that answer is not `localized` either, the
frame is dead-reckoned (its estimate is the prediction). Without a
calibrator on the server (`p_registered` null) the score alone decides and the full search's
answer is kept. With --odometry (a file in poses.txt's layout, e.g. a wheel or visual odometry's
camera-0 poses for the same frame indices, any origin; or `poses`, the sequence's own, i.e. the
truth) each prediction takes the camera's motion from it instead, as `cmr-agent track --odometry`
does (its simulated noise, --odometry-noise-*, is that command's alone).

The map region must already be stored on the server (PUT /v1/maps/{id}) in the sequence's map
frame: the LiDAR's frame at the sequence's frame 0 (see docs/tracking.md).

    python3 scripts/track-http.py --server http://localhost:8080 --id drive \
        --sequence data/drive/00 --out /tmp/track-http

Writes OUT/trajectory.kitti.txt (poses.txt convention: world_from_cam0, world = cam0 at frame
0), OUT/frames.csv and OUT/summary.json (ATE = RMSE of camera-centre errors, no alignment; RPE
between consecutive frames), and prints the summary. Exit status 1 on any HTTP or input error.
"""

import argparse
import base64
import csv
import json
import math
import os
import random
import sys
import time
import urllib.error
import urllib.request

# --- rigid 4x4 transforms as nested lists -------------------------------------------------------


def mul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


def inv(t):
    r = [[t[j][i] for j in range(3)] for i in range(3)]  # R^T
    p = [-sum(r[i][k] * t[k][3] for k in range(3)) for i in range(3)]
    return [r[0] + [p[0]], r[1] + [p[1]], r[2] + [p[2]], [0.0, 0.0, 0.0, 1.0]]


def from_3x4(values):
    return [values[0:4], values[4:8], values[8:12], [0.0, 0.0, 0.0, 1.0]]


def centre(camera_from_map):
    """Camera centre in the map frame: -R^T t."""
    m = inv(camera_from_map)
    return m[0][3], m[1][3], m[2][3]


def angle_deg(t):
    cos = max(-1.0, min(1.0, (t[0][0] + t[1][1] + t[2][2] - 1.0) / 2.0))
    return math.degrees(math.acos(cos))


def ground_motion(yaw, dx, dy):
    c, s = math.cos(yaw), math.sin(yaw)
    return [[c, -s, 0.0, dx], [s, c, 0.0, dy], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


# --- the sequence ---------------------------------------------------------------------------------


def read_sequence(root):
    calib = {}
    with open(os.path.join(root, "calib.txt")) as f:
        for line in f:
            if ":" in line:
                key, values = line.split(":", 1)
                calib[key.strip()] = [float(v) for v in values.split()]
    p2 = calib["P2"]
    tr = from_3x4(calib.get("Tr", calib.get("Tr_velo_to_cam")))
    if "R0_rect" in calib:
        r = calib["R0_rect"]
        tr = mul([r[0:3] + [0.0], r[3:6] + [0.0], r[6:9] + [0.0], [0, 0, 0, 1.0]], tr)
    offset = [[1.0, 0, 0, p2[3] / p2[0]], [0, 1.0, 0, p2[7] / p2[5]], [0, 0, 1.0, p2[11]], [0, 0, 0, 1.0]]
    poses = read_poses(os.path.join(root, "poses.txt"))
    images = sorted(n for n in os.listdir(os.path.join(root, "image_2")) if n.endswith(".png"))
    return {
        "intrinsics": {"fx": p2[0], "fy": p2[5], "cx": p2[2], "cy": p2[6]},
        "cam0_from_lidar": tr,  # C, rectified
        "camera_from_lidar": mul(offset, tr),  # image_2
        "poses": poses,  # world_from_cam0
        "images": [(int(n[:-4]), os.path.join(root, "image_2", n)) for n in images],
    }


def read_poses(path):
    """A poses.txt-layout file: one world_from_cam0 (3x4, row-major) per line."""
    with open(path) as f:
        return [from_3x4([float(v) for v in line.split()]) for line in f if line.strip()]


def truth_camera_from_map(seq, index, poses=None):
    """image_2's camera_from_map; the map frame is the LiDAR at frame 0: C^-1 W_k C. `poses`
    (world_from_cam0 per frame index) in place of the sequence's own, e.g. an odometry's."""
    c = seq["cam0_from_lidar"]
    map_from_lidar = mul(mul(inv(c), (poses or seq["poses"])[index]), c)
    return mul(seq["camera_from_lidar"], inv(map_from_lidar))


def world_from_cam0(seq, camera_from_map):
    c = seq["cam0_from_lidar"]
    map_from_lidar = mul(inv(camera_from_map), seq["camera_from_lidar"])
    return mul(mul(c, map_from_lidar), inv(c))


def perturbed(truth, shift_m, direction, yaw):
    """`truth` (camera_from_map) with its camera moved `shift_m` along the ground in `direction`
    and turned by `yaw` about map z through its own centre (radians)."""
    cx, cy, _ = centre(truth)
    mx, my = cx + shift_m * math.cos(direction), cy + shift_m * math.sin(direction)
    turned = (math.cos(yaw) * cx - math.sin(yaw) * cy, math.sin(yaw) * cx + math.cos(yaw) * cy)
    q = ground_motion(yaw, mx - turned[0], my - turned[1])
    return mul(truth, inv(q))


def coarse_prior(truth, noise_m, noise_deg, rng):
    direction = rng.uniform(0.0, 2.0 * math.pi)
    yaw = math.radians(noise_deg if rng.random() < 0.5 else -noise_deg)
    return perturbed(truth, noise_m, direction, yaw)


def predict(motion, last):
    """The last estimate moved again by the camera's motion per frame (standing still without one)."""
    return last if motion is None else mul(motion, last)


def measures_motion(earlier, later):
    """Whether the step between two consecutive frames' modes is motion, not a correction
    (src/track/mod.rs, `measures_motion`)."""
    if "dead_reckoning" in (earlier, later) or later == "cold":
        return False
    return later == "tracked" or earlier in ("cold", "fallback")


def last_motion(modes, estimates):
    """T_j T_{j-1}^-1 of the latest consecutive pair whose step is motion (src/track/mod.rs,
    `last_motion`); None before there is one."""
    for j in range(len(modes) - 1, 0, -1):
        if measures_motion(modes[j - 1], modes[j]):
            return mul(estimates[j], inv(estimates[j - 1]))
    return None


def along_axis(pose, d):
    """camera_from_map `pose` with the camera moved d metres along its own optical axis (forward
    positive; src/agent/search.rs, `AxisStarts::along_axis`)."""
    if d == 0.0:
        return pose
    return mul([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -d], [0.0, 0.0, 0.0, 1.0]], pose)


# --- HTTP -----------------------------------------------------------------------------------------


def localize(server, map_id, image_b64, intrinsics, prior, hypotheses, iterations, axis_starts=None):
    """(pose, confidence, latency in ms, the answer's start's shift along the axis in metres), or
    None when the server refuses the request's values (422: in a drive, the prior or a start along
    its axis outside the region, or too few points around it; `cmr-agent track` does the same)."""
    request = {
        "image": image_b64,
        "intrinsics": intrinsics,
        "prior_camera_from_map": prior,
        "hypotheses": hypotheses,
        "max_iterations": iterations,
    }
    if axis_starts is not None:
        request["axis_starts"] = axis_starts
    body = json.dumps(request).encode()
    request = urllib.request.Request(f"{server}/v1/maps/{map_id}/localize", data=body, headers={"Content-Type": "application/json"})
    started = time.perf_counter()
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            answer = json.load(response)
    except urllib.error.HTTPError as e:
        detail = e.read().decode(errors="replace")
        if e.code == 422:
            print(f"refused: {detail}", file=sys.stderr)
            return None
        raise SystemExit(f"localize failed: HTTP {e.code}: {detail}")
    latency_ms = (time.perf_counter() - started) * 1000.0
    shift = answer["hypotheses"][answer["chosen_hypothesis"]]["start_axis_shift_m"]
    return answer["pose"]["camera_from_map"], answer["confidence"], latency_ms, shift


def trusted(confidence):
    """The answer's verdict: `localized`, or None when the server has no calibrator (p_registered null)."""
    return None if confidence.get("p_registered") is None else bool(confidence["localized"])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", default="http://localhost:8080")
    parser.add_argument("--id", required=True, help="map region id on the server")
    parser.add_argument("--sequence", required=True, help="KITTI-layout sequence directory")
    parser.add_argument("--out", required=True)
    parser.add_argument("--first", type=int, default=0, help="first frame (file index)")
    parser.add_argument("--frames", type=int, default=None, help="frames to follow (default: all)")
    parser.add_argument("--prior-noise-m", type=float, default=5.0)
    parser.add_argument("--prior-noise-deg", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tracked-hypotheses", type=int, default=1)
    parser.add_argument("--tracked-iterations", type=int, default=3)
    parser.add_argument("--full-hypotheses", type=int, default=4)
    parser.add_argument("--full-iterations", type=int, default=10)
    parser.add_argument("--fallback-below", type=float, default=0.3)
    parser.add_argument("--tracked-axis-starts", type=int, default=2)
    parser.add_argument("--tracked-axis-step-m", type=float, default=1.25)
    parser.add_argument("--tracked-axis-margin", type=float, default=0.005)
    parser.add_argument("--odometry", default=None, metavar="poses|FILE",
                        help="predict with this odometry's motion (poses.txt layout) instead of constant velocity")
    args = parser.parse_args()

    seq = read_sequence(args.sequence)
    frames = [(i, path) for i, path in seq["images"] if i >= args.first][: args.frames]
    if not frames:
        raise SystemExit(f"{args.sequence}: no frames from {args.first} on")
    rng = random.Random(args.seed)
    odometry = None
    if args.odometry is not None:
        odometry = seq["poses"] if args.odometry == "poses" else read_poses(args.odometry)
        if len(odometry) <= frames[-1][0]:
            raise SystemExit(f"--odometry {args.odometry}: {len(odometry)} poses, the drive needs frame {frames[-1][0]}")
    rows, estimates, modes = [], [], []
    for position, (index, path) in enumerate(frames):
        with open(path, "rb") as f:
            image_b64 = base64.b64encode(f.read()).decode()
        truth = truth_camera_from_map(seq, index)
        full = (args.full_hypotheses, args.full_iterations)
        if position == 0:
            prior = coarse_prior(truth, args.prior_noise_m, args.prior_noise_deg, rng)
            first = localize(args.server, args.id, image_b64, seq["intrinsics"], prior, *full)
            if first is None:
                raise SystemExit("the first frame's prior was refused (outside the mapped area?)")
            pose, answer, latency, _ = first
            mode, tracked_confidence, shift = "cold", None, None
        else:
            if odometry is None:
                motion = last_motion(modes, estimates)
            else:  # C_k C_k-1^-1 in the odometry's own frame, as src/track/mod.rs's Odometry::motion
                motion = mul(truth_camera_from_map(seq, index, odometry), inv(truth_camera_from_map(seq, frames[position - 1][0], odometry)))
            prior = predict(motion, estimates[-1])
            axis = {"each_way": args.tracked_axis_starts, "step_m": args.tracked_axis_step_m, "margin": args.tracked_axis_margin}
            small = localize(args.server, args.id, image_b64, seq["intrinsics"], prior, args.tracked_hypotheses, args.tracked_iterations, axis)
            mode, tracked_confidence, shift, start, latency = "tracked", None, None, prior, 0.0
            if small is not None:
                pose, answer, latency, shift = small
                start, tracked_confidence = along_axis(prior, shift), answer["score"]
            if small is None or answer["score"] < args.fallback_below or trusted(answer) is False:
                again = localize(args.server, args.id, image_b64, seq["intrinsics"], start, *full)
                mode = "fallback"
                if again is not None:
                    pose, answer, more, _ = again
                    latency += more
                if again is None or trusted(answer) is False:
                    pose, mode = prior, "dead_reckoning"
                    answer = answer if again is not None else {"score": 0.0, "p_registered": None, "localized": False}
        confidence = answer["score"]
        estimates.append(pose)
        modes.append(mode)
        est, gt = centre(pose), centre(truth)
        row = {
            "position": position, "frame": index, "mode": mode, "confidence": confidence,
            "tracked_confidence": tracked_confidence, "axis_shift_m": shift, "latency_ms": latency,
            "p_registered": answer.get("p_registered"), "localized": answer.get("localized"),
            "position_error_m": math.dist(est, gt), "rpe_translation_m": None, "rpe_rotation_deg": None,
            "estimate_x": est[0], "estimate_y": est[1], "truth_x": gt[0], "truth_y": gt[1],
        }
        if position > 0:
            # E = (T_gt,k-1 T_gt,k^-1)^-1 (T_est,k-1 T_est,k^-1), as in src/track/metrics.rs.
            previous_truth = truth_camera_from_map(seq, frames[position - 1][0])
            e = mul(inv(mul(previous_truth, inv(truth))), mul(estimates[-2], inv(pose)))
            row["rpe_translation_m"] = math.hypot(e[0][3], e[1][3], e[2][3])
            row["rpe_rotation_deg"] = angle_deg(e)
        rows.append(row)
        print(f"frame {index}: {mode}, confidence {confidence:.2f}, error {row['position_error_m']:.3f} m, {latency:.0f} ms", file=sys.stderr)

    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "trajectory.kitti.txt"), "w") as f:
        for pose in estimates:
            w = world_from_cam0(seq, pose)
            f.write(" ".join(f"{v:.12e}" for v in w[0] + w[1] + w[2]) + "\n")
    with open(os.path.join(args.out, "frames.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    rpe_t = [r["rpe_translation_m"] for r in rows[1:]]
    rpe_r = [r["rpe_rotation_deg"] for r in rows[1:]]
    later = [r["latency_ms"] for r in rows[1:]]
    rms = lambda v: math.sqrt(sum(x * x for x in v) / len(v)) if v else 0.0
    summary = {
        "frames": len(rows),
        "ate_rmse_m": rms([r["position_error_m"] for r in rows]),
        "rpe_translation_rmse_m": rms(rpe_t),
        "rpe_rotation_rmse_deg": rms(rpe_r),
        "fallbacks": sum(r["mode"] == "fallback" for r in rows),
        "dead_reckoned": sum(r["mode"] == "dead_reckoning" for r in rows),
        "first_frame_ms": rows[0]["latency_ms"],
        "mean_per_frame_ms": sum(later) / len(later) if later else 0.0,
    }
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
