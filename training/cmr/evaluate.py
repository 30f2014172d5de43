"""Validation with the paper's protocol on held-out frames: RTE / RRE (Euler sum and geodesic) / RR
after each iteration 1..K for the agent (argmax policy) and for the greedy expert, plus what limits
them: frustum-head precision/recall and embedding match accuracy. With `--hypotheses H` > 1 the agent
runs the multi-start search (H yaw offsets about the map pivot, answer = highest alignment score,
`episodes.multi_start`) and the single-start figures are kept as `agent_single_start`.

    python -m cmr.evaluate --checkpoint runs/default/best.pt --data ../data/synth-test --out eval.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from . import geometry as g
from .data import find_sequences, list_frames, make_sample
from .episodes import embed, multi_start, rollout
from .models import STRIDE


def _summarise(errors: list[dict]) -> dict:
    rte = np.array([e["rte_m"] for e in errors])
    eul = np.array([e["rre_euler_deg"] for e in errors])
    geo = np.array([e["rre_geodesic_deg"] for e in errors])
    ok = (eul < g.RR_MAX_ROTATION_DEG) & (rte < g.RR_MAX_TRANSLATION_M)
    return dict(rte_m=float(rte.mean()), rre_euler_deg=float(eul.mean()), rre_geodesic_deg=float(geo.mean()),
                rr=float(ok.mean()), rte_median_m=float(np.median(rte)), rre_euler_median_deg=float(np.median(eul)))


def per_iteration(traj, truths) -> list[dict]:
    out = []
    for k in range(1, len(traj.poses)):
        errs = [g.pose_error(p, t) for p, t in zip(traj.poses[k], truths)]
        out.append(dict(iteration=k, **_summarise(errs)))
    return out


def frustum_confusion(logits: np.ndarray, samples) -> np.ndarray:
    """[true positives, false positives, false negatives] of the frustum head (logit > 0) against
    the samples' in-view labels, summed over the batch."""
    counts = np.zeros(3, dtype=np.int64)
    for s, lg in zip(samples, logits):
        pred = lg > 0
        counts += [int((pred & s.labels).sum()), int((pred & ~s.labels).sum()), int((~pred & s.labels).sum())]
    return counts


def precision_recall(counts: np.ndarray) -> dict:
    tp, fp, fn = (int(c) for c in counts)
    return dict(precision=tp / max(tp + fp, 1), recall=tp / max(tp + fn, 1))


@torch.no_grad()
def match_accuracy(episodes, samples, max_points: int = 512) -> float:
    """Share of true-frustum points whose most similar image cell (over the whole 40x128 map) lies
    within one cell of where the point really projects."""
    hits, total = 0, 0
    for i, s in enumerate(samples):
        idx = np.flatnonzero(s.labels)[:max_points]
        if len(idx) == 0:
            continue
        uv, _ = g.project(s.intrinsics, g.transform(s.truth, s.points[idx].astype(np.float64)))
        cell = np.floor((uv + 0.5) / STRIDE)
        feats = episodes.point_features[i, torch.as_tensor(idx)]
        grid = episodes.image_features[i].flatten(1)  # [64, H*W]
        best = (feats @ grid).argmax(dim=1).cpu().numpy()
        w = episodes.image_features.shape[-1]
        pred = np.stack([best % w, best // w], axis=1)
        hits += int((np.abs(pred - cell).max(axis=1) <= 1).sum())
        total += len(idx)
    return hits / max(total, 1)


@torch.no_grad()
def evaluate_embeddings(models: dict, frames, seed: int = 1234, num_points: int = 40960, chunk: int = 4,
                        device: torch.device | str = "cpu") -> dict:
    """Stage 1 alone (no rollouts): match accuracy and the frustum head's precision / recall on
    `frames`, with the same samples `evaluate` draws for them."""
    device = torch.device(device)
    for m in models.values():
        m.eval()
    confusion = np.zeros(3, dtype=np.int64)
    match_hits = []
    for start in range(0, len(frames), chunk):
        samples = [make_sample(f, np.random.default_rng([seed, start + j]), train=False, num_points=num_points)
                   for j, f in enumerate(frames[start:start + chunk])]
        eps = embed(models, samples, device)
        logits = models["frustum_head"](eps.point_features, eps.image_features).cpu().numpy()
        confusion += frustum_confusion(logits, samples)
        match_hits.append((match_accuracy(eps, samples), len(samples)))
    return dict(frames=len(frames), frustum=precision_recall(confusion),
                match_accuracy=float(sum(a * n for a, n in match_hits) / max(sum(n for _, n in match_hits), 1)))


@torch.no_grad()
def evaluate(models: dict, frames, seed: int = 1234, iterations: int = 10, num_points: int = 40960,
             chunk: int = 4, device: torch.device | str = "cpu", motions: list | None = None,
             hypotheses: int = 1, action_frame: str = g.CAMERA_Y) -> dict:
    """`motions`: one Q per frame (frozen cases, e.g. the Rust harness's); random ones otherwise.
    `hypotheses` > 1: `agent` is the multi-start search's selected poses, `agent_single_start`
    hypothesis 0 (the paper's single trajectory). 1 runs the plain rollout and scores nothing, so
    training's periodic validation pays nothing for the search. `action_frame`: the model's (the
    expert acts in the same frame)."""
    device = torch.device(device)
    for m in models.values():
        m.eval()
    agent_errors: list[list] = [[] for _ in range(iterations)]
    expert_errors: list[list] = [[] for _ in range(iterations)]
    single_errors: list[list] = [[] for _ in range(iterations)]
    confusion = np.zeros(3, dtype=np.int64)
    match_hits = []
    initial: list[dict] = []
    for start in range(0, len(frames), chunk):
        samples = [make_sample(f, np.random.default_rng([seed, start + j]), train=False, num_points=num_points,
                               motion=None if motions is None else motions[start + j])
                   for j, f in enumerate(frames[start:start + chunk])]
        eps = embed(models, samples, device, action_frame)
        logits = models["frustum_head"](eps.point_features, eps.image_features).cpu().numpy()
        confusion += frustum_confusion(logits, samples)
        match_hits.append((match_accuracy(eps, samples), len(samples)))
        initial.extend(g.pose_error(p, t) for p, t in zip(eps.initial, eps.truth))
        runs = [(expert_errors, rollout(None, eps, iterations, "expert").poses[1:])]
        if hypotheses == 1:
            runs.append((agent_errors, rollout(models["agent"], eps, iterations, "greedy").poses[1:]))
        else:
            selected, trajectories = multi_start(models["agent"], eps, iterations, hypotheses)
            runs += [(agent_errors, selected), (single_errors, trajectories[0].poses[1:])]
        for errors, poses in runs:
            for k in range(iterations):
                errors[k].extend(g.pose_error(p, t) for p, t in zip(poses[k], eps.truth))
    table = lambda errors: [dict(iteration=k + 1, **_summarise(e)) for k, e in enumerate(errors)]  # noqa: E731
    result = dict(
        frames=len(frames), seed=seed, hypotheses=hypotheses, action_frame=action_frame,
        initial=_summarise(initial),
        agent=table(agent_errors),
        expert=table(expert_errors),
        frustum=precision_recall(confusion),
        match_accuracy=float(sum(a * n for a, n in match_hits) / max(sum(n for _, n in match_hits), 1)),
    )
    if hypotheses > 1:
        result["agent_single_start"] = table(single_errors)
    return result


def frozen_cases(frames: list, path: Path) -> tuple[list, list]:
    """The frames and motions Q of a perturbations file (format cmr-agent-perturbations/1)."""
    doc = json.loads(Path(path).read_text())
    if doc.get("format") != "cmr-agent-perturbations/1":
        raise SystemExit(f"{path}: not a cmr-agent-perturbations/1 file")
    by_key = {(f.sequence.name, f.index): f for f in frames}
    picked, motions = [], []
    for case in doc["cases"]:
        frame = by_key.get((case["sequence"], case["frame"]))
        if frame is None:
            raise SystemExit(f"{path}: sequence {case['sequence']} frame {case['frame']} is not in the data")
        picked.append(frame)
        motions.append(g.ground_motion(math.radians(case["yaw_deg"]), case["dx_m"], case["dy_m"]))
    return picked, motions


def main(argv=None) -> None:
    from .export import action_frame_of, load_models
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="KITTI-layout root or sequence directory")
    ap.add_argument("--frames", type=int, default=0, help="evaluate at most this many frames (0 = all)")
    ap.add_argument("--seed", type=int, default=1234)
    ap.add_argument("--perturbations", type=Path,
                    help="the Rust harness's frozen cases (docs/eval/perturbations.json): evaluate exactly those")
    ap.add_argument("--hypotheses", type=int, default=1,
                    help="multi-start search: H starts turned about the map pivot, answer = best alignment "
                         "(1 = the paper's single start)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    models, meta = load_models(args.checkpoint)
    frames = list_frames(find_sequences(args.data))
    motions = None
    if args.perturbations:
        frames, motions = frozen_cases(frames, args.perturbations)
    if args.frames:
        step = max(1, len(frames) // args.frames)
        frames = frames[::step][: args.frames]
        if motions is not None:
            motions = motions[::step][: args.frames]
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    models = {k: m.to(device) for k, m in models.items()}
    result = evaluate(models, frames, seed=args.seed, motions=motions, hypotheses=args.hypotheses,
                      action_frame=action_frame_of(meta), device=device)
    text = json.dumps(result, indent=2)
    if args.out:
        from .export import atomic_write_bytes
        atomic_write_bytes(args.out, (text + "\n").encode())
    print(text)


if __name__ == "__main__":
    main()
