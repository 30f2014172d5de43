"""Does the 2D state carry an alignment signal? For held-out frames, score a pose by the mean cosine
similarity between each in-view point's feature and the image feature of the cell it projects to,
and count how often the true pose outscores the same pose perturbed by a given yaw or shift.

A perfect embedding wins every comparison; a useless one wins about half. This is the number the
agent's 2D branch lives on, so it is checked before spending hours on the agent stage.

Two global figures say how well the score would judge the whole search space, without an agent:
- `heading_at_truth`: at the true camera centre, the best of 72 headings (5 deg apart, turned about
  map z) is within 10 deg of the truth (share of frames; `cmr.heading_sweep --truth` does the
  same on ONNX sets, turning about camera y);
- `truth_percentile`: the share of `--global-poses` poses drawn as the paper's protocol draws its
  starts (any heading, the camera within +-10 m in the ground plane), registered ones (5 m /
  10 deg) left out, that score below the truth (mean over frames; 0.5 = no signal), and
  `truth_beats_all`: the share of frames where the truth outscores every one of them.

And where the score peaks near the truth, the floor of any search's position error: `peak` scores
a grid about the true pose (`PEAK_YAWS_DEG` turns about the camera centre, times ground shifts on
a 1 m lattice within `PEAK_RADIUS_M`; 405 poses) and gives the best pose's camera-centre distance
from the truth (mean, median, share within 1 m) and the share of frames where it has the true
heading.

    python -m cmr.diagnose --checkpoint runs/default/last.pt --data ../data/synth-val --frames 24
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from . import geometry as g
from .data import find_sequences, list_frames, make_sample
from .episodes import embed
from .evaluate import frustum_confusion, precision_recall

# (name, yaw degrees, tx metres, tz metres) in the camera frame, applied about the scan centroid.
PERTURBATIONS = [("yaw+2", 2, 0, 0), ("yaw-5", -5, 0, 0), ("yaw+20", 20, 0, 0), ("yaw-90", -90, 0, 0),
                 ("yaw180", 180, 0, 0), ("tx+0.5", 0, 0.5, 0), ("tx-2", 0, -2, 0), ("tz+2", 0, 0, 2),
                 ("tz-5", 0, 0, -5)]


def alignment_score(eps, row: int, pose: np.ndarray) -> float:
    """`state.alignment` of one pose for one row (the score the multi-start search ranks by)."""
    return float(eps.alignment([pose], [row])[0])


SWEEP_DEG = np.arange(0.0, 360.0, 5.0)  # the headings of `heading_at_truth`
PEAK_YAWS_DEG = (-6.0, -3.0, 0.0, 3.0, 6.0)  # the turns of `peak`'s grid
PEAK_RADIUS_M = 5  # its ground shifts: a 1 m lattice within this radius


def global_poses(truth: np.ndarray, rng: np.random.Generator, count: int) -> tuple[list[np.ndarray], np.ndarray]:
    """`SWEEP_DEG` headings at the true camera centre, then `count` protocol-like poses (heading
    uniform, ground shift uniform in +-10 m); and a mask of the latter that are not registered."""
    centre = g.invert(truth)[:3, 3]
    sweep = [g.apply_action(truth, centre, yaw, 0.0, 0.0, frame=g.MAP_Z) for yaw in SWEEP_DEG]
    drawn, far = [], []
    for _ in range(count):
        pose = g.protocol_pose(truth, rng)
        drawn.append(pose)
        far.append(not g.registered(pose, truth))
    return sweep + drawn, np.asarray(far)


def peak_grid(truth: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """`peak`'s poses about `truth` (camera_from_map): each turn of `PEAK_YAWS_DEG` about the camera
    centre (map z), then each ground shift of the lattice (right, forward of the turned heading);
    with each pose's camera-centre distance from the truth (m) and whether its turn is 0."""
    centre = g.invert(truth)[:3, 3]
    r = PEAK_RADIUS_M
    shifts = [(x, z) for x in range(-r, r + 1) for z in range(-r, r + 1) if x * x + z * z <= r * r]
    poses, turn_zero = [], []
    for yaw in PEAK_YAWS_DEG:
        turned = g.apply_action(truth, centre, yaw, 0.0, 0.0, frame=g.MAP_Z)
        for x, z in shifts:
            poses.append(g.apply_action(turned, centre, 0.0, float(x), float(z), frame=g.MAP_Z))
            turn_zero.append(yaw == 0.0)
    dist = np.array([np.linalg.norm(g.invert(p)[:3, 3] - centre) for p in poses])
    return poses, dist, np.asarray(turn_zero)


@torch.no_grad()
def diagnose(models: dict, frames, seed: int = 4321, num_points: int = 40960, chunk: int = 4,
             global_count: int = 128) -> dict:
    for m in models.values():
        m.eval()
    heading_hits, percentiles, beats_all = 0, [], 0
    peak_dist, peak_heading = [], []
    wins = {name: 0 for name, *_ in PERTURBATIONS}
    margins = {name: [] for name, *_ in PERTURBATIONS}
    confusion = np.zeros(3, dtype=np.int64)
    for start in range(0, len(frames), chunk):
        samples = [make_sample(f, np.random.default_rng([seed, start + j]), train=False, num_points=num_points)
                   for j, f in enumerate(frames[start:start + chunk])]
        eps = embed(models, samples, torch.device("cpu"))
        logits = models["frustum_head"](eps.point_features, eps.image_features).numpy()
        confusion += frustum_confusion(logits, samples)
        for row, s in enumerate(samples):
            truth_score = alignment_score(eps, row, s.truth)
            for name, yaw, tx, tz in PERTURBATIONS:
                moved = g.apply_action(s.truth, eps.pivots[row], yaw, tx, tz)
                margin = truth_score - alignment_score(eps, row, moved)
                wins[name] += margin > 0
                margins[name].append(margin)
            poses, far = global_poses(s.truth, np.random.default_rng([seed, 7, start + row]), global_count)
            scores = eps.alignment(poses, [row] * len(poses))
            n_sweep = len(SWEEP_DEG)
            best = SWEEP_DEG[int(np.argmax(scores[:n_sweep]))]
            heading_hits += min(best, 360.0 - best) <= g.RR_MAX_ROTATION_DEG
            others = scores[n_sweep:][far]
            percentiles.append(float((others < truth_score).mean()) if len(others) else 1.0)
            beats_all += bool((others < truth_score).all())
            grid, dist, turn_zero = peak_grid(s.truth)
            best = int(np.argmax(eps.alignment(grid, [row] * len(grid))))
            peak_dist.append(float(dist[best]))
            peak_heading.append(bool(turn_zero[best]))
    n = len(frames)
    return dict(frames=n, frustum=precision_recall(confusion),
                heading_at_truth=heading_hits / n, truth_percentile=float(np.mean(percentiles)),
                truth_beats_all=beats_all / n,
                peak=dict(distance_mean_m=float(np.mean(peak_dist)), distance_median_m=float(np.median(peak_dist)),
                          within_1m=float(np.mean(np.asarray(peak_dist) <= 1.0 + 1e-9)),
                          heading_right=float(np.mean(peak_heading))),
                truth_wins={k: v / n for k, v in wins.items()},
                median_margin={k: float(np.median(v)) for k, v in margins.items()})


def main(argv=None) -> None:
    from .export import load_models
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--global-poses", type=int, default=128, help="protocol-like poses per frame for truth_percentile")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    models, _ = load_models(args.checkpoint)
    frames = list_frames(find_sequences(args.data))
    frames = frames[:: max(1, len(frames) // args.frames)][: args.frames]
    print(json.dumps(diagnose(models, frames, global_count=args.global_poses), indent=2))


if __name__ == "__main__":
    main()
