"""Registration episodes on frozen one-shot embeddings: batching samples, rolling out a policy
(agent, expert, or a DAgger mix of both), and the per-step reward."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from . import geometry as g
from .data import Sample, point_input
from .models import point_channels_of
from .state import NUM_STATE_POINTS, alignment, build_state

REWARD_POINTS = 1024  # true-frustum points used for the point-to-point distance


@dataclass
class Episodes:
    """B samples with their one-shot embeddings, stacked as tensors on one device."""
    points: torch.Tensor  # [B, N, 3]
    point_features: torch.Tensor  # [B, N, 64]
    image_features: torch.Tensor  # [B, 64, 40, 128]
    frustum_prob: torch.Tensor  # [B, M]
    intrinsics: torch.Tensor  # [B, 4]
    truth: list[np.ndarray]
    initial: list[np.ndarray]
    pivots: list[np.ndarray]
    reward_points: list[np.ndarray]
    # The axes the actions act along (g.ACTION_FRAMES); the manifest's `actions.frame`.
    action_frame: str = g.CAMERA_Y

    def __len__(self) -> int:
        return len(self.truth)

    def subset(self, rows: list[int]) -> "Episodes":
        idx = torch.as_tensor(rows, device=self.points.device)
        pick = lambda xs: [xs[i] for i in rows]  # noqa: E731
        return Episodes(self.points[idx], self.point_features[idx], self.image_features[idx], self.frustum_prob[idx],
                        self.intrinsics[idx], pick(self.truth), pick(self.initial), pick(self.pivots),
                        pick(self.reward_points), self.action_frame)

    def replace(self, rows: list[int], other: "Episodes") -> None:
        """Overwrite entries `rows` with `other` (same order): the agent stage's rolling pool."""
        idx = torch.as_tensor(rows, device=self.points.device)
        for name in ("points", "point_features", "image_features", "frustum_prob", "intrinsics"):
            getattr(self, name)[idx] = getattr(other, name)
        for name in ("truth", "initial", "pivots", "reward_points"):
            mine, theirs = getattr(self, name), getattr(other, name)
            for j, r in enumerate(rows):
                mine[r] = theirs[j]

    def state(self, poses: list[np.ndarray], rows: list[int] | None = None):
        rows = list(range(len(self))) if rows is None else rows
        idx = torch.as_tensor(rows, device=self.points.device)
        pose_t = torch.as_tensor(np.stack(poses), dtype=torch.float32, device=self.points.device)
        return build_state(pose_t, self.points[idx], self.intrinsics[idx], self.point_features[idx],
                           self.image_features[idx], self.frustum_prob[idx])

    @torch.no_grad()
    def alignment(self, poses: list[np.ndarray], rows: list[int] | None = None) -> np.ndarray:
        """`state.alignment` of one pose per row (all rows by default) -> float array [len(poses)]."""
        rows = list(range(len(self))) if rows is None else rows
        idx = torch.as_tensor(rows, device=self.points.device)
        pose_t = torch.as_tensor(np.stack(poses), dtype=torch.float32, device=self.points.device)
        return alignment(pose_t, self.points[idx], self.intrinsics[idx], self.point_features[idx],
                         self.image_features[idx]).cpu().numpy()


@torch.no_grad()
def degrade_image_features(episodes: Episodes, share: float, sigma_max: float, rng: np.random.Generator) -> None:
    """Weakens the image evidence of a `share` of the rows, in place: each chosen row's features
    get Gaussian noise of a standard deviation drawn uniformly in [0, sigma_max] per component, and
    every cell's vector is normalised again (the encoder's output is unit length). With D = 64
    channels a unit feature keeps about 1 / sqrt(1 + 64 sigma^2) of itself along the truth: 0.35
    gives a third, what the alignment signal keeps on real frames of drives training never read
    against synthetic ones (training/README.md). The agent then learns to act on evidence as weak
    as the held-out real frames give it. Draws from `rng` only (reproducible per iteration)."""
    if share <= 0.0 or sigma_max <= 0.0:
        return
    feats = episodes.image_features
    for row in range(len(episodes)):
        if rng.random() >= share:
            continue
        sigma = float(rng.uniform(0.0, sigma_max))
        noise = torch.from_numpy(rng.standard_normal(tuple(feats.shape[1:])).astype(np.float32)).to(feats.device)
        noisy = feats[row] + sigma * noise
        feats[row] = noisy / noisy.norm(dim=0, keepdim=True).clamp_min(1e-12)


@torch.no_grad()
def embed(models: dict, samples: list[Sample], device: torch.device, action_frame: str = g.CAMERA_Y) -> Episodes:
    points = torch.as_tensor(np.stack([s.points for s in samples]), device=device)
    images = torch.as_tensor(np.stack([s.image for s in samples]), device=device)
    encoder = models["point_encoder"]
    pf = encoder(torch.as_tensor(point_input(samples, point_channels_of(encoder)), device=device))
    imf = models["image_encoder"](images)
    prob = torch.sigmoid(models["frustum_head"](pf, imf))[:, :NUM_STATE_POINTS]
    reward_points = []
    for s in samples:
        inside = s.points[s.labels].astype(np.float64)
        reward_points.append(inside[:REWARD_POINTS] if len(inside) else s.points[:REWARD_POINTS].astype(np.float64))
    return Episodes(points=points, point_features=pf, image_features=imf, frustum_prob=prob,
                    intrinsics=torch.as_tensor(np.stack([s.intrinsics for s in samples]), dtype=torch.float32, device=device),
                    truth=[s.truth for s in samples], initial=[s.initial for s in samples],
                    pivots=[s.points.astype(np.float64).mean(axis=0) for s in samples], reward_points=reward_points,
                    action_frame=g.check_frame(action_frame))


def embed_many(models: dict, samples: list[Sample], device: torch.device, chunk: int = 4,
               action_frame: str = g.CAMERA_Y) -> Episodes:
    """`embed` in chunks (the point encoder's activations for 40,960 points are large)."""
    parts = [embed(models, samples[i:i + chunk], device, action_frame) for i in range(0, len(samples), chunk)]
    cat = lambda name: torch.cat([getattr(p, name) for p in parts])  # noqa: E731
    join = lambda name: [x for p in parts for x in getattr(p, name)]  # noqa: E731
    return Episodes(cat("points"), cat("point_features"), cat("image_features"), cat("frustum_prob"),
                    cat("intrinsics"), join("truth"), join("initial"), join("pivots"), join("reward_points"),
                    g.check_frame(action_frame))


def step_pose(pose: np.ndarray, pivot: np.ndarray, action, frame: str = g.CAMERA_Y) -> np.ndarray:
    return g.apply_action(pose, pivot, *g.step_values(action), frame=frame)


@dataclass
class Trajectory:
    poses: list[list[np.ndarray]]  # [T+1][B] pose before each step (and the final one)
    actions: np.ndarray  # [T, B, 3]
    experts: np.ndarray  # [T, B, 3]
    log_probs: np.ndarray  # [T, B]
    values: np.ndarray  # [T+1, B]
    rewards: np.ndarray  # [T, B]
    states: list | None = None  # [T] of the agent's observation (Agent.correlate volume, state_3d) for the update


@torch.no_grad()
def rollout(agent, episodes: Episodes, steps: int, mode: str = "greedy", expert_mix: float = 0.0,
            rng: np.random.Generator | None = None, generator: torch.Generator | None = None,
            keep_states: bool = False) -> Trajectory:
    """mode: 'greedy' (argmax), 'sample' (stochastic policy), 'expert' (greedy expert, no agent
    needed). With expert_mix > 0, each env takes the expert's action with that probability (DAgger)."""
    b = len(episodes)
    poses = [list(episodes.initial)]
    actions = np.zeros((steps, b, 3), dtype=np.int64)
    experts = np.zeros((steps, b, 3), dtype=np.int64)
    log_probs = np.zeros((steps, b), dtype=np.float32)
    values = np.zeros((steps + 1, b), dtype=np.float32)
    rewards = np.zeros((steps, b), dtype=np.float32)
    states = [] if keep_states else None
    for t in range(steps + 1):
        current = poses[-1]
        if agent is not None:
            state_2d, state_3d = episodes.state(current)
            observation = (agent.correlate(state_2d), state_3d)
            logits, value = agent.decide(*observation)
            values[t] = value[:, 0].cpu().numpy()
            if keep_states and t < steps:
                states.append(observation)
        if t == steps:
            break
        expert = np.array([g.expert_indices(p, episodes.truth[i], episodes.pivots[i], episodes.action_frame)
                           for i, p in enumerate(current)])
        experts[t] = expert
        if mode == "expert" or agent is None:
            chosen = expert
        else:
            dist = torch.distributions.Categorical(logits=logits)
            if mode == "sample":
                chosen = torch.multinomial(dist.probs.reshape(-1, logits.shape[-1]), 1, generator=generator).view(b, 3).cpu().numpy()
            else:
                chosen = logits.argmax(dim=-1).cpu().numpy()
            if expert_mix > 0:
                take = rng.random(b) < expert_mix
                chosen = np.where(take[:, None], expert, chosen)
            log_probs[t] = dist.log_prob(torch.as_tensor(chosen, device=logits.device)).sum(-1).cpu().numpy()
        actions[t] = chosen
        nxt = []
        for i, p in enumerate(current):
            q = step_pose(p, episodes.pivots[i], chosen[i], episodes.action_frame)
            before = g.p2p_distance(p, episodes.truth[i], episodes.reward_points[i])
            after = g.p2p_distance(q, episodes.truth[i], episodes.reward_points[i])
            rewards[t, i] = g.step_reward(before, after)
            nxt.append(q)
        poses.append(nxt)
    return Trajectory(poses, actions, experts, log_probs, values, rewards, states)


def select_hypotheses(scores: np.ndarray) -> np.ndarray:
    """scores [H, T, B] -> the best-scoring hypothesis per iteration and row [T, B]; ties go to the
    lowest index (argmax keeps the first), so hypothesis 0, the prior itself, wins a draw."""
    return np.asarray(scores).argmax(axis=0)


def multi_start(agent, episodes: Episodes, steps: int, hypotheses: int,
                keep_states: bool = False) -> tuple[list[list[np.ndarray]], list[Trajectory]]:
    """The multi-start search: greedy rollouts from the prior turned about the map pivot by each of
    `g.start_yaw_offsets(hypotheses)` (a single start fails on coarse yaw), and after each iteration
    1..steps the pose of the hypothesis with the highest alignment score. Returns (selected poses
    [steps][B], the H trajectories, with the agent's observations when `keep_states`).
    `episodes.initial` is restored afterwards."""
    prior = list(episodes.initial)
    trajectories, scores = [], []
    try:
        for off in g.start_yaw_offsets(hypotheses):
            episodes.initial = [g.apply_action(p, episodes.pivots[i], off, 0.0, 0.0, frame=episodes.action_frame)
                                for i, p in enumerate(prior)]
            traj = rollout(agent, episodes, steps, "greedy", keep_states=keep_states)
            trajectories.append(traj)
            scores.append([episodes.alignment(traj.poses[t]) for t in range(1, steps + 1)])
    finally:
        episodes.initial = prior
    pick = select_hypotheses(np.array(scores))
    selected = [[trajectories[pick[t, i]].poses[t + 1][i] for i in range(len(episodes))] for t in range(steps)]
    return selected, trajectories


def gae(rewards: np.ndarray, values: np.ndarray, gamma: float, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Advantages and returns; the episode is truncated at T, so the last value bootstraps."""
    steps = rewards.shape[0]
    adv = np.zeros_like(rewards)
    running = np.zeros(rewards.shape[1], dtype=np.float32)
    for t in reversed(range(steps)):
        delta = rewards[t] + gamma * values[t + 1] - values[t]
        running = delta + gamma * lam * running
        adv[t] = running
    return adv, adv + values[:-1]
