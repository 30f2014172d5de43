"""Would an exhaustive heading sweep fix the search's answer? An offline experiment (issue 13).

For each frozen case: the multi-start search in PyTorch (`episodes.multi_start`, 4 starts, 10
iterations; not the server's search, which also merges duplicates, so its base RR is lower), then
the alignment score (`state.alignment`) of the final pose turned about its own camera centre by
every multiple of `--step` degrees, and the best of those; then 10 more greedy agent steps from
the swept pose, and a second sweep. With `--truth`, the sweep at the true pose alone (how often
the alignment score's best heading at the right position is within 10 deg).

    python -m cmr.heading_sweep --models ../models --data ../../shared/real-dev --perturbations ../docs/eval/real-dev-perturbations.json
    python -m cmr.heading_sweep --models ../models --data ../data/synth-val --perturbations ../docs/eval/val-perturbations.json --every 3

Prints RR (10 deg / 5 m) of: the search's answer, the swept pose, the agent after it, the second
sweep, and the highest-scoring of the four.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from . import geometry as g
from .data import find_sequences, list_frames, make_sample
from .episodes import embed, multi_start, rollout
from .evaluate import frozen_cases
from .import_onnx import import_models


def sweep(eps, pose: np.ndarray, yaws: np.ndarray) -> tuple[np.ndarray, float]:
    """The best-aligned of `pose` turned about its camera centre by each of `yaws` (degrees)."""
    centre = g.invert(pose)[:3, 3]
    poses = [g.apply_action(pose, centre, y, 0.0, 0.0, frame=g.CAMERA_Y) for y in yaws]
    scores = eps.alignment(poses, [0] * len(poses))
    k = int(np.argmax(scores))
    return poses[k], float(scores[k])


@torch.no_grad()
def run(models: dict, frames: list, motions: list, step_deg: float, every: int, truth_only: bool) -> dict:
    yaws = np.arange(-180.0, 180.0, step_deg)
    names = ["truth_sweep"] if truth_only else ["search", "sweep", "sweep_then_agent", "second_sweep", "best_scoring"]
    hits = dict.fromkeys(names, 0)
    cases = 0
    for i, (frame, motion) in enumerate(zip(frames, motions)):
        if i % every:
            continue
        sample = make_sample(frame, np.random.default_rng([1234, i]), train=False, motion=motion)
        eps = embed(models, [sample], torch.device("cpu"))
        truth = sample.truth
        cases += 1
        if truth_only:
            hits["truth_sweep"] += g.registered(sweep(eps, truth, yaws)[0], truth)
            continue
        selected, _ = multi_start(models["agent"], eps, 10, 4)
        answer = selected[-1][0]
        swept, swept_score = sweep(eps, answer, yaws)
        prior = eps.initial
        eps.initial = [swept]
        walked = rollout(models["agent"], eps, 10, "greedy").poses[-1][0]
        eps.initial = prior
        again, again_score = sweep(eps, walked, yaws)
        scored = [(float(eps.alignment([answer], [0])[0]), answer), (swept_score, swept),
                  (float(eps.alignment([walked], [0])[0]), walked), (again_score, again)]
        for name, pose in zip(names, [answer, swept, walked, again, max(scored, key=lambda x: x[0])[1]]):
            hits[name] += g.registered(pose, truth)
    return dict(cases=cases, step_deg=step_deg, rr={k: v / max(cases, 1) for k, v in hits.items()})


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--perturbations", type=Path, required=True, help="frozen cases (cmr-agent-perturbations/1)")
    ap.add_argument("--step", type=float, default=5.0, help="sweep step, degrees")
    ap.add_argument("--every", type=int, default=1, help="every k-th case")
    ap.add_argument("--truth", action="store_true", help="sweep at the true pose only")
    args = ap.parse_args(argv)
    models, _ = import_models(args.models)
    frames, motions = frozen_cases(list_frames(find_sequences(args.data)), args.perturbations)
    print(json.dumps(run(models, frames, motions, args.step, args.every, args.truth), indent=2))


if __name__ == "__main__":
    main()
