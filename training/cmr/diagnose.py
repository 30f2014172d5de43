"""Does the 2D state carry an alignment signal? For held-out frames, score a pose by the mean cosine
similarity between each in-view point's feature and the image feature of the cell it projects to,
and count how often the true pose outscores the same pose perturbed by a given yaw or shift.

A perfect embedding wins every comparison; a useless one wins about half. This is the number the
agent's 2D branch lives on, so it is checked before spending hours on the agent stage.

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


@torch.no_grad()
def diagnose(models: dict, frames, seed: int = 4321, num_points: int = 40960, chunk: int = 4) -> dict:
    for m in models.values():
        m.eval()
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
    n = len(frames)
    return dict(frames=n, frustum=precision_recall(confusion),
                truth_wins={k: v / n for k, v in wins.items()},
                median_margin={k: float(np.median(v)) for k, v in margins.items()})


def main(argv=None) -> None:
    from .export import load_models
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=24)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    models, _ = load_models(args.checkpoint)
    frames = list_frames(find_sequences(args.data))
    frames = frames[:: max(1, len(frames) // args.frames)][: args.frames]
    print(json.dumps(diagnose(models, frames), indent=2))


if __name__ == "__main__":
    main()
