#!/usr/bin/env python3
"""Which scores tell the camera's position along its optical axis on real frames? (issue 29)

For every frame of KITTI-layout roots, the true camera_from_map (the frame's own scan as the map)
is moved along the camera's optical axis by d in [-5, 5] m (0.25 m apart) and sideways by x in
[-2, 2] m (0.125 m apart), and each score is evaluated at every pose:
- `edges`: Levinson & Thrun's edge alignment (RSS 2013), the classic rig-independent score of
  targetless camera-LiDAR calibration: LiDAR points where the range jumps by more than 0.3 m to
  a neighbour on the same scan ring (neighbours: adjacent azimuth within 0.6 deg, elevation within
  0.08 deg, so any point order works), weighted by sqrt(jump), projected into the image's edge
  map (the largest grey difference to the 8 neighbours, spread by an inverse distance transform,
  gamma 0.98, alpha 1/3); the weighted mean over the points in view;
- with `--models`: the learned alignment score (`cmr.state.alignment`: the mean over the map's
  points in view of dot(point feature, image cell feature); the set's graphs imported as float
  modules), and the same with each point weighted by 1 / depth (`inverse-depth`) or 1 / depth^1.5.

Prints per score (and per rig with `--rigs`): the mean and median distance of the forward profile's
peak from the truth, the share within 1 m, how often the truth beats the pose 2 m and 5 m ahead
and behind, and the mean sideways peak distance. A score that tells the position peaks at 0.

With `--cases` (a `cmr-agent eval --record-hypotheses` cases.json of one root, and its
`--perturbations` file): a replay from the search's answers instead of the truth. Each answer moved
along its own optical axis to the best of [-3, 3] m (0.25 m apart) by each learned score, and the
best final pose of the hypotheses by each score: RR (10 deg / 5 m), the registered answers' mean
RTE and every answer's median RTE.

    cd training && ../.venv/bin/python ../scripts/depth-cues.py ../../shared/real-dev \\
        ~/.cache/cmr-agent/data/real-split/val --models ../models
    cd training && ../.venv/bin/python ../scripts/depth-cues.py ../../shared/real-train \\
        --rigs ~/.cache/cmr-agent/data/real-split/rigs.json     # edges only: every rig
    cd training && ../.venv/bin/python ../scripts/depth-cues.py ../../shared/real-dev --models ../models \\
        --perturbations ../docs/eval/real-dev-perturbations.json --cases /tmp/ev/rec-dev/cases.json
"""

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "training"))
from cmr import geometry as g  # noqa: E402
from cmr.data import find_sequences, list_frames, make_sample  # noqa: E402
from cmr.state import frustum_cells, to_camera  # noqa: E402

FORWARD = np.arange(-5, 5.001, 0.25)
SIDEWAYS = np.arange(-2, 2.001, 0.125)


def moved(pose: np.ndarray, x: float = 0.0, z: float = 0.0) -> np.ndarray:
    """camera_from_map of the camera moved by x (right) and z (forward), its own frame."""
    t = np.eye(4)
    t[0, 3], t[2, 3] = -x, -z
    return t @ pose


def lidar_edges(xyz: np.ndarray, bin_deg=0.08, max_daz=0.6, min_jump=0.3):
    """(points, weights): scan points nearer than a same-ring neighbour by more than `min_jump` m."""
    r = np.linalg.norm(xyz, axis=1)
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    el = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    jump = np.zeros(len(r))
    for offset in (0.0, 0.5):  # two bin grids, so that a ring on a bin edge finds its neighbours
        b = np.floor(el / bin_deg + offset).astype(np.int64)
        order = np.lexsort((az, b))
        bo, ao, ro, eo = b[order], az[order], r[order], el[order]
        same = (bo[1:] == bo[:-1]) & (np.abs(ao[1:] - ao[:-1]) < max_daz) & (np.abs(eo[1:] - eo[:-1]) < bin_deg)
        d = ro[1:] - ro[:-1]
        j = np.zeros(len(ro))
        j[:-1] = np.maximum(j[:-1], np.where(same, d, 0))
        j[1:] = np.maximum(j[1:], np.where(same, -d, 0))
        jump[order] = np.maximum(jump[order], j)
    keep = jump > min_jump
    return xyz[keep], np.sqrt(jump[keep])


def edge_map(grey: np.ndarray, gamma=0.98, alpha=1 / 3, reach_px=40) -> np.ndarray:
    img = torch.from_numpy(grey)[None, None]
    pad = torch.nn.functional.pad(img, (1, 1, 1, 1), mode="replicate")
    h, w = grey.shape
    e = torch.zeros_like(img)
    for dy in range(3):
        for dx in range(3):
            if (dy, dx) != (1, 1):
                e = torch.maximum(e, (pad[..., dy:dy + h, dx:dx + w] - img).abs())
    spread = e.clone()
    for _ in range(reach_px):
        spread = torch.maximum(e, gamma * torch.nn.functional.max_pool2d(spread, 3, 1, 1))
    return (alpha * e + (1 - alpha) * spread)[0, 0].numpy()


def edge_score(field, k, points, weights, pose) -> float:
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    z = cam[:, 2]
    ok = z > 1.0
    safe = np.where(ok, z, 1.0)
    u, v = k[0] * cam[:, 0] / safe + k[2], k[1] * cam[:, 1] / safe + k[3]
    h, w = field.shape
    ok &= (u >= 0) & (u < w - 0.5) & (v >= 0) & (v < h - 0.5)
    if ok.sum() < 20:
        return -np.inf
    vals = field[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)]
    return float((weights[ok] * vals).sum() / weights[ok].sum())


@torch.no_grad()
def learned_scores(models, sample, poses) -> dict:
    """The alignment score at each pose, unweighted and weighted by depth^-p."""
    from cmr.episodes import embed
    eps = embed(models, [sample], torch.device("cpu"))
    p = torch.as_tensor(np.stack(poses), dtype=torch.float32)
    cam = to_camera(p, eps.points.float().expand(len(poses), -1, -1))
    cell, inside = frustum_cells(eps.intrinsics.expand(len(poses), -1), cam)
    cells = eps.image_features.flatten(2).transpose(1, 2)[0].float()
    cells = torch.cat([cells, torch.zeros(1, cells.shape[1])])
    dots = (eps.point_features[0].float()[None] * cells[cell]).sum(-1)
    depth = cam[..., 2].clamp(min=1.0)
    out = {}
    for name, power in (("learned", 0.0), ("learned, inverse-depth", 1.0), ("learned, depth^-1.5", 1.5)):
        w = torch.where(inside, depth ** -power, torch.zeros_like(depth))
        out[name] = ((dots * w).sum(1) / w.sum(1).clamp(min=1e-9)).numpy()
    return out


def summary(rows: list[dict]) -> str:
    fw = np.abs([r["forward_peak"] for r in rows])
    side = np.abs([r["sideways_peak"] for r in rows])
    beats = {k: np.mean([r["beats"][k] for r in rows]) for k in rows[0]["beats"]}
    return (f"{len(rows):3d} frames  forward peak |d| mean {fw.mean():.2f} m, median {np.median(fw):.2f} m, "
            f"within 1 m {np.mean(fw <= 1):.2f}; truth beats " + ", ".join(f"{k} {v:.2f}" for k, v in beats.items())
            + f"; sideways peak |x| mean {side.mean():.2f} m")


def replay(models, root: Path, perturbations: Path, cases: Path) -> None:
    """The search's answers polished along the optical axis, or rechosen, by each learned score."""
    frames = {(f.image_path.parent.parent.name, int(f.image_path.stem)): f for f in list_frames(find_sequences(root))}
    motions = json.loads(perturbations.read_text())["cases"]
    records = [r for r in json.loads(cases.read_text()) if r["method"] == "cmr-agent"]
    if len(records) != len(motions):
        raise SystemExit(f"{cases}: {len(records)} cases, {perturbations}: {len(motions)}")
    pose = lambda m: np.vstack([np.asarray(m, float).reshape(3, 4), [0, 0, 0, 1]])  # noqa: E731
    shifts = np.arange(-3, 3.001, 0.25)
    results = defaultdict(list)  # rule -> (registered, rte)
    for i, (rec, q) in enumerate(zip(records, motions)):
        motion = g.ground_motion(np.radians(q["yaw_deg"]), q["dx_m"], q["dy_m"])
        sample = make_sample(frames[(q["sequence"], q["frame"])], np.random.default_rng([1234, i]), train=False, motion=motion)
        truth, answer = pose(rec["notes"]["truth_camera_from_map"]), pose(rec["notes"]["answer_camera_from_map"])
        finals = [answer] + [pose((h["steps"] or [h["start"]])[-1]["camera_from_map"]) for h in rec["notes"]["hypotheses"]]
        chosen = {"the search's answer": answer}
        at_finals = learned_scores(models, sample, finals)
        for name, scores in at_finals.items():
            chosen[f"best final pose by {name}"] = finals[int(np.argmax(scores))]
            along = [moved(answer, z=d) for d in shifts]
            chosen[f"answer moved along the axis by {name}"] = along[int(np.argmax(learned_scores(models, sample, along)[name]))]
        for rule, p in chosen.items():
            results[rule].append((g.registered(p, truth), g.pose_error(p, truth)["rte_m"]))
    for rule, r in results.items():
        a = np.array(r, float)
        ok = a[:, 0] > 0
        print(f"{rule:52s} RR {ok.mean():.3f} ({int(ok.sum())}/{len(a)}), RTE of the registered {a[ok, 1].mean():.2f} m, "
              f"median RTE {np.median(a[:, 1]):.2f} m")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("roots", nargs="+", type=Path, help="KITTI-layout roots (sequences/NN/...)")
    ap.add_argument("--models", type=Path, help="a model set: also the learned scores")
    ap.add_argument("--rigs", type=Path, help="rigs.json of cmr.real_split: figures per rig too")
    ap.add_argument("--cases", type=Path, help="replay a cmr-agent eval --record-hypotheses cases.json (needs --models)")
    ap.add_argument("--perturbations", type=Path, help="with --cases: its perturbation file")
    args = ap.parse_args()
    torch.set_num_threads(2)
    models = None
    if args.models:
        from cmr.import_onnx import import_models
        models, _ = import_models(args.models)
    if args.cases:
        if models is None or not args.perturbations or len(args.roots) != 1:
            raise SystemExit("--cases needs --models, --perturbations and one root")
        replay(models, args.roots[0], args.perturbations, args.cases)
        return
    rig_of = {seq: v["rig"] for seq, v in json.loads(args.rigs.read_text()).items()} if args.rigs else {}
    rows = defaultdict(list)  # (score, group) -> per-frame results
    for n, frame in enumerate(list_frames([s for root in args.roots for s in find_sequences(root)])):
        seq = frame.image_path.parent.parent
        calib = frame.calib
        truth = calib.camera_from_lidar
        fw_poses = [moved(truth, z=d) for d in FORWARD]
        side_poses = [moved(truth, x=x) for x in SIDEWAYS]
        grey = np.asarray(Image.open(frame.image_path).convert("L"), dtype=np.float32)
        xyz = np.fromfile(frame.scan_path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
        points, weights = lidar_edges(xyz)
        field = edge_map(grey)
        profiles = {"edges": ([edge_score(field, calib.intrinsics, points, weights, p) for p in fw_poses],
                              [edge_score(field, calib.intrinsics, points, weights, p) for p in side_poses])}
        if models is not None:
            # the model's input: the image resized and cropped, the map the frame's own scan sampled
            sample = make_sample(frame, np.random.default_rng([1234, n]), train=False, motion=np.eye(4))
            fw_l = learned_scores(models, sample, [moved(sample.truth, z=d) for d in FORWARD])
            side_l = learned_scores(models, sample, [moved(sample.truth, x=x) for x in SIDEWAYS])
            profiles.update({k: (fw_l[k], side_l[k]) for k in fw_l})
        zero = len(FORWARD) // 2
        for name, (fw, side) in profiles.items():
            fw = np.asarray(fw)
            result = dict(forward_peak=float(FORWARD[int(np.argmax(fw))]), sideways_peak=float(SIDEWAYS[int(np.argmax(side))]),
                          beats={f"{d:+g} m": bool(fw[zero] > fw[int(np.argmin(np.abs(FORWARD - d)))]) for d in (2, -2, 5, -5)})
            rows[(name, "all")].append(result)
            if seq.name in rig_of:
                rows[(name, rig_of[seq.name])].append(result)
        print(f"{seq.name}: " + ", ".join(f"{k} {FORWARD[int(np.argmax(v[0]))]:+.2f} m" for k, v in profiles.items()),
              file=sys.stderr, flush=True)
    for (name, group), r in sorted(rows.items(), key=lambda kv: (kv[0][1] != "all", kv[0])):
        print(f"{name:24s} {group:12s} {summary(r)}")


if __name__ == "__main__":
    main()
