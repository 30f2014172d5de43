"""Training in two stages, resumable from the run directory.

1. embed: point encoder + image encoder with the circle loss over 2D-3D correspondences, and the
   frustum head with weighted BCE, on samples built with the paper's protocol.
2. agent: embeddings frozen (one-shot, as at serving time). Each iteration rolls out episodes on
   fresh samples and updates the agent with behaviour cloning of the greedy expert on the states
   it visited (DAgger: a decaying share of steps follows the expert); after `bc_only_iters` the
   PPO loss (GAE, point-to-point reward) joins the BC loss.

    python -m cmr.train --data ../data/synth-train --out runs/default [--set key=value ...]

Re-running the same command resumes from `<out>/last.pt`. Every step appends to `<out>/log.jsonl`
(one JSON object per line; `python -m cmr.plots <out>` draws the curves).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import geometry as g
from .augment import AugmentOptions
from .data import find_sequences, list_frames, make_sample, point_input, split_frames
from .episodes import degrade_image_features, embed, embed_many, gae, rollout
from .export import atomic_write_bytes
from .losses import circle_loss, weighted_bce
from .models import STRIDE, arch_of, build_all, load_pretrained

# The span of the near hard negatives (`Config.rank_near_pool`): `cmr.diagnose`'s peak grid turns
# up to 6 deg and shifts up to 5 m; the turn here reaches a little beyond it.
NEAR_TURN_DEG = 8.0
NEAR_SHIFT_M = 5.0


@dataclass
class Config:
    data: str = ""  # comma-separated KITTI-layout roots / sequence dirs
    val_data: str = ""  # held-out root; when empty every `holdout_every`-th training frame
    holdout_every: int = 10
    out: str = "runs/default"
    seed: int = 0
    num_points: int = 40960
    threads: int = 2
    # The action frame the agent is trained in and the manifest names (geometry.ACTION_FRAMES):
    # "camera_y" (yaw about camera y; every model up to v3) or "map_z" (yaw about the map's up axis).
    action_frame: str = "camera_y"
    # stage 1: embeddings
    embed_steps: int = 1500
    embed_points: int = 16384  # N while training the encoders (speed); features are density-robust
    embed_batch: int = 2
    embed_lr: float = 1e-3
    # Stage-1 schedule: "constant" (every model up to v3) or "cosine" (linear warm-up over
    # `embed_warmup` steps, then cosine from embed_lr to embed_lr_min at embed_steps).
    embed_schedule: str = "constant"
    embed_warmup: int = 0
    embed_lr_min: float = 1e-5
    embed_grad_clip: float = 0.0  # max gradient norm in stage 1 (0: no clipping)
    # Stage 1 with the BatchNorm layers in evaluation mode (their running statistics fixed, the
    # affine parameters still learned): for fine-tuning, where batch statistics at batch 2 would
    # change the function at step 0 (an imported model's BatchNorm is folded to identity statistics).
    embed_frozen_bn: bool = False
    # The encoders' normalisation (models.NORMS): "batch" (up to v3) or "group" (per-sample statistics).
    norm: str = "batch"
    # Optional, off: the image encoder also sees its input's luma gradient magnitude, computed in
    # the graph (the ONNX input stays [1, 3, 160, 512] RGB).
    image_edges: bool = False
    # The image encoder (models.IMAGE_BACKBONES): "scratch" (every model up to v10) or
    # "efficientnet_lite0" (ImageNet-pretrained backbone, loaded at the start of a run that is not
    # initialised from a checkpoint), whose pretrained weights learn at backbone_lr_scale x the rate.
    image_backbone: str = "scratch"
    # The point encoder (models.POINT_ENCODERS): "pillars" (every model up to v14) or
    # "pillars_fine" (a second, 0.4 m grid; from a "pillars" checkpoint it starts at zero) or
    # "pillars_intensity" (each point's intensity rank as a fifth input cue; from "pillars" its
    # weights start at zero).
    point_encoder: str = "pillars"
    backbone_lr_scale: float = 0.1
    circle_points: int = 512
    circle_radius_cells: float = 1.0
    circle_scale: float = 10.0
    circle_pos_margin: float = 0.1
    circle_neg_margin: float = 1.4
    bce_weight: float = 1.0
    # Optional, off: a ranking term on the alignment score the search and `cmr.diagnose` use (mean
    # point-image agreement over the points in view): the true pose must outscore `rank_poses`
    # perturbed ones (yaw 2-30 deg, camera-frame shifts 0.3-3 m) by `rank_margin`, softplus-hinged.
    rank_weight: float = 0.0
    rank_poses: int = 4
    rank_margin: float = 0.05
    # Share of those perturbations drawn wide instead: a turn of 30-180 deg either way about the
    # vertical through the camera centre and a ground shift of up to `rank_far_shift_m` in any
    # direction (map_z frame) -- the real-frame failures are flipped headings and metres backwards.
    rank_far: float = 0.0
    rank_far_shift_m: float = 6.0
    # Hard negatives, off: `rank_hard_pool` poses drawn per sample as the paper's protocol draws its
    # starts (any heading about the camera centre, a ground shift within +-10 m; registered ones
    # redrawn), scored without gradient, and the `rank_hard` best-scoring of them added to the
    # perturbed poses -- the wrong poses the search would answer with (the street seen backwards).
    # `rank_hard_points` as `rank_near_points` below, for this pool.
    rank_hard_pool: int = 0
    rank_hard: int = 0
    rank_hard_points: int = 0
    # Near hard negatives, off: `rank_near_pool` poses drawn per sample about the truth over the
    # span of `cmr.diagnose`'s peak grid (a turn within +-`NEAR_TURN_DEG` about the camera centre,
    # then a ground shift of 1 to `NEAR_SHIFT_M` m), scored without gradient, and the
    # `rank_near_hard` best-scoring of them added to the perturbed poses with their own margin
    # `rank_near_margin` -- the poses a position peak metres off the truth is made of. With
    # 0 < `rank_near_points` < the sample's points, the pool is scored on that many of them (one
    # random subset per sample, the same for every pose of its pool), so that a large pool stays
    # cheap; otherwise on all of them.
    rank_near_pool: int = 0
    rank_near_hard: int = 0
    rank_near_margin: float = 0.02
    rank_near_points: int = 0
    # Feature distillation, off: with `distill_weight` > 0 stage 1 adds `distill_weight` times the
    # mean cosine distance (1 - cos) between this run's embeddings and those a frozen teacher (the
    # point and image encoders of checkpoint `distill_from`) gives the same batch, per point and per
    # image cell, so that a fine-tune keeps what its start knew where the other terms ask for no
    # change (Li & Hoiem, "Learning without Forgetting", TPAMI 2018, in feature form).
    distill_weight: float = 0.0
    distill_from: str = ""
    # stage 2: agent
    agent_iters: int = 2000
    agent_envs: int = 8
    pool_size: int = 48  # embedded samples kept for rollouts (embedding is the slow part on CPU)
    pool_refresh: int = 2  # samples replaced per iteration
    rollout_steps: int = 10
    agent_lr: float = 1e-3
    agent_lr_min: float = 5e-5  # cosine decay from agent_lr over agent_iters (equal values: constant)
    bc_only_iters: int = 300
    expert_mix_start: float = 0.5
    expert_mix_iters: int = 300
    update_epochs: int = 1
    minibatch: int = 40
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    ppo_weight: float = 0.5
    value_weight: float = 0.5
    entropy_weight: float = 0.01
    # Exponential moving average of the agent's weights, per iteration (0: off). Validation,
    # best.pt and export use the average: nearby checkpoints of the live weights differ by several
    # RR points, and the average smooths that update noise away.
    agent_ema: float = 0.0
    # Augmentation for transfer (augment.AugmentOptions; the defaults are today's behaviour)
    photometric: str = "basic"  # "heavy": exposure, contrast, white balance, gamma, hue, saturation,
    #                             greyscale, channel shuffle, blur, noise, JPEG
    scale_max: float = 1.0  # random zoom in [1, scale_max] before the random crop, intrinsics following
    lidar_aug: bool = False  # beam dropout, density, range noise, an occluded azimuth sector
    beams_min: int = 16
    beams_max: int = 32
    beam_dropout_p: float = 0.5
    density_min: float = 0.3
    range_noise_m: float = 0.03
    occlusion_p: float = 0.3
    occlusion_max_deg: float = 60.0
    # Maps from other scans of the drive (data.neighbour_map; needs poses.txt): a region built from
    # a drive does not have its scan centre at the camera. 0 = each frame's own scan (v3).
    map_window: int = 0
    map_scans: int = 3
    map_window_p: float = 1.0  # share of training samples with such a map; the rest keep their own scan
    # The server's crop of a tiled region seen from a prior off the camera (data.virtual_scan_map):
    # that share of the samples; map_window / map_scans choose the union it is cut from.
    virtual_scan_p: float = 0.0
    virtual_scan_offset_m: float = 6.0
    virtual_scan_radius_m: float = 60.0
    # Fleet-like starts for a share of the samples (augment.AugmentOptions.near_start_p): yaw within
    # +-near_start_yaw_deg, ground shift within near_start_shift_m, instead of the protocol's.
    near_start_p: float = 0.0
    near_start_yaw_deg: float = 30.0
    near_start_shift_m: float = 5.0
    # Mirror augmentation (augment.AugmentOptions.mirror_p): this share of the samples flipped left
    # to right, image and map together.
    mirror_p: float = 0.0
    # Intensity dropout (augment.AugmentOptions.intensity_drop_p): this share of the samples reads
    # a map without intensity (rank 0.5 everywhere); for "pillars_intensity" encoders.
    intensity_drop_p: float = 0.0
    # Stage 2 only, off: this share of the rollout pool's samples with their image features made
    # noisy (episodes.degrade_image_features, per-component std up to image_noise_max), so the
    # agent also learns on evidence as weak as real frames of unseen drives give it.
    image_noise_p: float = 0.0
    image_noise_max: float = 0.35
    # Start from another run's checkpoint (its weights only; optimisers and counters start fresh):
    # fine-tuning. Ignored when <out>/last.pt exists (resume wins).
    init_from: str = ""
    # Then the agent alone (its moving average when saved) from this checkpoint, whatever its
    # encoders: a trained policy on new embeddings (the correlation it reads is a cosine either way).
    init_agent_from: str = ""
    # bookkeeping
    # Wall-time budgets per stage (0: none). With a budget the stage ends when it is spent and its
    # cosine runs over max(step share, time share); meant for one-shot runs (scripts/train-gpu.sh).
    embed_seconds: float = 0.0
    agent_seconds: float = 0.0
    loader_workers: int = 0  # processes that build training samples ahead of the step (0: in the loop)
    embed_eval_every: int = 0  # stage 1: match accuracy + frustum P/R on the validation frames every k steps (0: off)
    log_every: int = 10
    checkpoint_every: int = 50
    # Copies of the checkpoint kept aside (<out>/snap/embed_NNNNNN.pt, agent_NNNNN.pt) every k stage-1
    # steps / stage-2 iterations (0: none): the candidates a shipping rule names, which `last.pt`
    # alone would overwrite.
    keep_embed_every: int = 0
    keep_agent_every: int = 0
    eval_every: int = 200
    eval_frames: int = 24

    @staticmethod
    def from_overrides(base: "Config", pairs: list[str]) -> "Config":
        fields = {f.name: f for f in dataclasses.fields(Config)}
        values = {}
        for pair in pairs:
            key, _, raw = pair.partition("=")
            if key not in fields:
                raise SystemExit(f"unknown config key {key!r}; known: {', '.join(fields)}")
            kind = type(getattr(base, key))
            values[key] = kind(raw) if kind is not bool else raw.lower() in ("1", "true", "yes")
        return dataclasses.replace(base, **values)


_LOADER: dict = {}


def points_subset(points: torch.Tensor, pf: torch.Tensor, count: int, rng) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` of one sample's points [N, 3] and their features [N, C], drawn without replacement
    by `rng` and kept in order, when 0 < `count` < N; otherwise both unchanged."""
    if 0 < count < len(points):
        keep = torch.as_tensor(np.sort(rng.choice(len(points), count, replace=False)), device=points.device)
        return points[keep], pf[keep]
    return points, pf


def build_samples(frames, seed: int, stage: int, step: int, count: int, num_points: int, augment) -> list:
    rng = np.random.default_rng([seed, stage, step])
    picks = rng.integers(0, len(frames), count)
    return [make_sample(frames[i], rng, train=True, num_points=num_points, augment=augment) for i in picks]


def _init_loader(frames, augment) -> None:
    torch.set_num_threads(1)
    _LOADER.update(frames=frames, augment=augment)


def _loader_batch(seed: int, stage: int, step: int, count: int, num_points: int) -> list:
    return build_samples(_LOADER["frames"], seed, stage, step, count, num_points, _LOADER["augment"])


class Run:
    """Owns the models, optimisers, the run directory, logging and checkpoints."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        g.check_frame(cfg.action_frame)
        self.dir = Path(cfg.out)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        torch.manual_seed(cfg.seed)
        self.models = {k: m.to(self.device) for k, m in build_all(**arch_of(dataclasses.asdict(cfg))).items()}
        if cfg.image_backbone != "scratch" and not cfg.init_from:
            print(f"image backbone {cfg.image_backbone}: {load_pretrained(self.models['image_encoder'])} pretrained tensors",
                  flush=True)
        self.augment = AugmentOptions(photometric=cfg.photometric, scale_max=cfg.scale_max, lidar=cfg.lidar_aug,
                                      beams_min=cfg.beams_min, beams_max=cfg.beams_max,
                                      beam_dropout_p=cfg.beam_dropout_p, density_min=cfg.density_min,
                                      range_noise_m=cfg.range_noise_m, occlusion_p=cfg.occlusion_p,
                                      occlusion_max_deg=cfg.occlusion_max_deg, map_window=cfg.map_window,
                                      map_scans=cfg.map_scans, map_window_p=cfg.map_window_p,
                                      virtual_scan_p=cfg.virtual_scan_p, virtual_scan_offset_m=cfg.virtual_scan_offset_m,
                                      virtual_scan_radius_m=cfg.virtual_scan_radius_m,
                                      near_start_p=cfg.near_start_p, near_start_yaw_deg=cfg.near_start_yaw_deg,
                                      near_start_shift_m=cfg.near_start_shift_m, mirror_p=cfg.mirror_p,
                                      intensity_drop_p=cfg.intensity_drop_p)
        self.opt_embed = torch.optim.Adam(self.embed_param_groups(), lr=cfg.embed_lr)
        self.opt_agent = torch.optim.Adam(self.models["agent"].parameters(), lr=cfg.agent_lr, betas=(0.98, 0.999))
        self.agent_ema = copy.deepcopy(self.models["agent"]).eval() if cfg.agent_ema > 0 else None
        self.teacher = self._teacher(Path(cfg.distill_from)) if cfg.distill_weight > 0 else None
        self.embed_step = 0
        self.agent_iter = 0
        self._pool, self._pending = None, {}
        self.best = None  # (rr, -rte) of the best validation so far
        frames = list_frames([s for root in cfg.data.split(",") if root for s in find_sequences(Path(root))])
        if cfg.val_data:
            self.train_frames = frames
            val = list_frames(find_sequences(Path(cfg.val_data)))
        else:
            self.train_frames, val = split_frames(frames, cfg.holdout_every)
        step = max(1, len(val) // max(cfg.eval_frames, 1))
        self.val_frames = val[::step][: cfg.eval_frames]
        if not (self.dir / "last.pt").exists():
            if cfg.init_from:
                self._init_from(Path(cfg.init_from))
            if cfg.init_agent_from:
                self._init_agent_from(Path(cfg.init_agent_from))
        self._load(self.dir / "last.pt")

    # -- persistence -------------------------------------------------------------------------
    def meta(self) -> dict:
        return dict(data=self.cfg.data, seeds=dict(train=self.cfg.seed), config=dataclasses.asdict(self.cfg),
                    training=dict(embed_steps=self.embed_step, agent_iters=self.agent_iter,
                                  train_frames=len(self.train_frames), val_frames=len(self.val_frames)))

    def save(self, name: str) -> None:
        state = dict(models={k: m.state_dict() for k, m in self.models.items()},
                     opt_embed=self.opt_embed.state_dict(), opt_agent=self.opt_agent.state_dict(),
                     embed_step=self.embed_step, agent_iter=self.agent_iter, best=self.best, meta=self.meta())
        if self.agent_ema is not None:
            state["agent_ema"] = self.agent_ema.state_dict()
        path = self.dir / name
        tmp = path.with_suffix(".tmp")
        torch.save(state, tmp)
        with open(tmp, "rb+") as f:
            import os
            os.fsync(f.fileno())
        tmp.replace(path)

    def keep(self, name: str) -> None:
        """A checkpoint like `last.pt`, kept as `<out>/snap/<name>`."""
        (self.dir / "snap").mkdir(exist_ok=True)
        self.save(f"snap/{name}")

    def _load(self, path: Path) -> None:
        if not path.exists():
            return
        state = torch.load(path, map_location=self.device, weights_only=False)
        for k, m in self.models.items():
            m.load_state_dict(state["models"][k])
        self.opt_embed.load_state_dict(state["opt_embed"])
        self.opt_agent.load_state_dict(state["opt_agent"])
        self.embed_step, self.agent_iter, self.best = state["embed_step"], state["agent_iter"], state["best"]
        if self.agent_ema is not None:
            # A run that turns the average on starts it from the live weights.
            self.agent_ema.load_state_dict(state.get("agent_ema", state["models"]["agent"]))
        print(f"resumed from {path}: embed step {self.embed_step}, agent iteration {self.agent_iter}", flush=True)

    def _init_from(self, path: Path) -> None:
        state = torch.load(path, map_location=self.device, weights_only=False)
        arch = arch_of(state.get("meta", {}).get("config", {}))
        mine = arch_of(dataclasses.asdict(self.cfg))
        # Encoders may grow from a checkpoint's, starting as it: a shallow EfficientNet-Lite0 encoder
        # its stride-32 stages (`LiteImageEncoder.load_shallow`), a pillar encoder its fine grid
        # or its intensity input (`PointEncoder.load_coarse`); each new branch's way into the output starts at zero. A
        # Lite0 encoder may also swap its backbone for Lite1's ImageNet weights, keeping its decoder
        # (`LiteImageEncoder.load_decoder`): that encoder starts anew, the rest of the model does not.
        grows = dict(image_backbone={("efficientnet_lite0", "efficientnet_lite0_s32"), ("efficientnet_lite0", "efficientnet_lite1")},
                     point_encoder={("pillars", "pillars_fine"), ("pillars", "pillars_intensity")})
        grown = {k for k, pairs in grows.items() if (arch[k], mine[k]) in pairs}
        if {k: v for k, v in arch.items() if k not in grown} != {k: v for k, v in mine.items() if k not in grown}:
            wanted = " ".join(f"{k}={v}" for k, v in arch.items())
            raise SystemExit(f"{path} was trained with {wanted}; pass --set {wanted}")
        for k, m in self.models.items():
            if k == "image_encoder" and "image_backbone" in grown and m.deep:
                print(f"deepened image encoder: {load_pretrained(m)} pretrained tensors, "
                      f"{m.load_shallow(state['models'][k])} from {path}", flush=True)
            elif k == "image_encoder" and "image_backbone" in grown:
                print(f"image backbone {m.variant}: {load_pretrained(m)} pretrained tensors, "
                      f"decoder {m.load_decoder(state['models'][k])} tensors from {path}", flush=True)
            elif k == "point_encoder" and "point_encoder" in grown:
                print(f"point encoder with {'intensity' if m.intensity else 'a fine grid'}: "
                      f"{m.load_coarse(state['models'][k])} tensors from {path}", flush=True)
            elif k != "agent":
                m.load_state_dict(state["models"][k])
        self._set_agent(state)
        print(f"initialised from {path} (embed step {state['embed_step']}, agent iteration {state['agent_iter']})",
              flush=True)

    def _teacher(self, path: Path) -> dict:
        """The frozen encoders of checkpoint `path` (same architecture as this run's), for
        `distill_weight`; read again on every resume, so the file must stay where it was."""
        state = torch.load(path, map_location=self.device, weights_only=False)
        if arch_of(state.get("meta", {}).get("config", {})) != arch_of(dataclasses.asdict(self.cfg)):
            raise SystemExit(f"the teacher {path} has another architecture than this run")
        built = build_all(**arch_of(dataclasses.asdict(self.cfg)))
        teacher = {}
        for k in ("point_encoder", "image_encoder"):
            m = built[k].to(self.device)
            m.load_state_dict(state["models"][k])
            teacher[k] = m.eval().requires_grad_(False)
        return teacher

    def _init_agent_from(self, path: Path) -> None:
        state = torch.load(path, map_location=self.device, weights_only=False)
        self._set_agent(state)
        print(f"agent initialised from {path} (agent iteration {state['agent_iter']})", flush=True)

    def _set_agent(self, state: dict) -> None:
        """The agent (and its moving average) from a checkpoint: the average when it was saved."""
        self.models["agent"].load_state_dict(state.get("agent_ema", state["models"]["agent"]))
        if self.agent_ema is not None:
            self.agent_ema.load_state_dict(self.models["agent"].state_dict())

    def log(self, record: dict) -> None:
        with open(self.dir / "log.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")

    # -- data --------------------------------------------------------------------------------
    def samples(self, stage: int, step: int, count: int, num_points: int):
        """The batch of (stage, step): the same whether built here or by a loader worker."""
        if self.cfg.loader_workers <= 0:
            return build_samples(self.train_frames, self.cfg.seed, stage, step, count, num_points, self.augment)
        if self._pool is None:
            import concurrent.futures as cf
            import multiprocessing as mp
            self._pool = cf.ProcessPoolExecutor(self.cfg.loader_workers, mp.get_context("fork"),
                                                initializer=_init_loader, initargs=(self.train_frames, self.augment))
        key = (stage, step, count, num_points)
        if key not in self._pending:
            self._pending[key] = self._pool.submit(_loader_batch, self.cfg.seed, *key)
        for ahead in range(1, self.cfg.loader_workers * 2 + 1 if stage in (1, 2) else 1):  # next steps, same stage
            nxt = (stage, step + ahead, count, num_points)
            if nxt not in self._pending:
                self._pending[nxt] = self._pool.submit(_loader_batch, self.cfg.seed, *nxt)
        out = self._pending.pop(key).result()
        for stale in [k for k in self._pending if k[0] != stage or k[1] < step]:
            self._pending.pop(stale).cancel()
        return out

    def close(self) -> None:
        """Stops the loader workers (prefetched batches are dropped)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._pending = None, {}

    def stage_progress(self, step: int, steps: int, started: float, seconds: float) -> float:
        """Share of a stage done: by steps, or by wall time when the stage has a time budget."""
        frac = step / max(steps, 1)
        if seconds > 0:
            frac = max(frac, (time.time() - started) / seconds)
        return min(1.0, frac)

    def embed_lr(self, step: int, progress: float | None = None) -> float:
        """Stage 1's learning rate at `step` (0-based); `progress` in [0, 1] overrides the step's
        share of the cosine (time-budgeted runs)."""
        cfg = self.cfg
        if cfg.embed_schedule == "constant":
            return cfg.embed_lr
        if cfg.embed_schedule != "cosine":
            raise SystemExit(f"unknown embed_schedule {cfg.embed_schedule!r}; expected constant or cosine")
        if step < cfg.embed_warmup:
            return cfg.embed_lr * (step + 1) / cfg.embed_warmup
        span = max(cfg.embed_steps - cfg.embed_warmup, 1)
        frac = min(1.0, (step - cfg.embed_warmup) / span) if progress is None else progress
        return cfg.embed_lr_min + 0.5 * (cfg.embed_lr - cfg.embed_lr_min) * (1 + math.cos(math.pi * frac))

    # -- stage 1 -----------------------------------------------------------------------------
    def embed_losses(self, samples) -> tuple[torch.Tensor, dict]:
        cfg, dev = self.cfg, self.device
        pe, ie, fh = self.models["point_encoder"], self.models["image_encoder"], self.models["frustum_head"]
        points = torch.as_tensor(np.stack([s.points for s in samples]), device=dev)
        encoder_in = torch.as_tensor(point_input(samples, pe.in_channels), device=dev)
        images = torch.as_tensor(np.stack([s.image for s in samples]), device=dev)
        labels = torch.as_tensor(np.stack([s.labels for s in samples]), device=dev)
        pf, imf = pe(encoder_in), ie(images)
        logits = fh(pf, imf)
        bce = weighted_bce(logits, labels)
        circles = []
        rng = np.random.default_rng([cfg.seed, 99, self.embed_step])
        for i, s in enumerate(samples):
            inside = np.flatnonzero(s.labels)
            if len(inside) < 8:
                continue
            pick = rng.choice(inside, min(cfg.circle_points, len(inside)), replace=False)
            p_cam = s.points[pick].astype(np.float64) @ s.truth[:3, :3].T + s.truth[:3, 3]
            uv = np.stack([s.intrinsics[0] * p_cam[:, 0] / p_cam[:, 2] + s.intrinsics[2],
                           s.intrinsics[1] * p_cam[:, 1] / p_cam[:, 2] + s.intrinsics[3]], axis=1)
            # grid_sample (align_corners=False) puts feature cell c's centre at pixel 4c + 1.5.
            norm = torch.as_tensor(np.stack([(uv[:, 0] + 0.5) / 256.0 - 1.0, (uv[:, 1] + 0.5) / 80.0 - 1.0], 1),
                                   dtype=torch.float32, device=dev)
            pix = F.grid_sample(imf[i:i + 1], norm.view(1, 1, -1, 2), align_corners=False).view(imf.shape[1], -1).t()
            pix = pix / pix.norm(dim=1, keepdim=True).clamp(min=1e-6)
            uv_cells = torch.as_tensor(uv / STRIDE, dtype=torch.float32, device=dev)
            circles.append(circle_loss(pf[i, torch.as_tensor(pick, device=dev)], pix, uv_cells, cfg.circle_radius_cells,
                                       cfg.circle_scale, cfg.circle_pos_margin, cfg.circle_neg_margin))
        circle = torch.stack(circles).mean() if circles else logits.sum() * 0.0
        with torch.no_grad():
            pred = logits > 0
            tp = (pred & labels).sum().item()
            stats = dict(precision=tp / max(pred.sum().item(), 1), recall=tp / max(labels.sum().item(), 1))
        loss = circle + cfg.bce_weight * bce
        if cfg.rank_weight > 0:
            rank = self.rank_loss(samples, points, pf, imf, rng)
            loss = loss + cfg.rank_weight * rank
            stats["rank"] = rank.item()
        if self.teacher is not None:
            distill = self.distill_loss(encoder_in, images, pf, imf)
            loss = loss + cfg.distill_weight * distill
            stats["distill"] = distill.item()
        return loss, dict(circle=circle.item(), bce=bce.item(), **stats)

    def distill_loss(self, points, images, pf, imf) -> torch.Tensor:
        """Mean cosine distance of point embeddings `pf` (B, N, C) and image embeddings `imf`
        (B, C, H, W) from the teacher's for the same `points` (the encoder's input) and `images` (0 = the teacher's
        directions; the point and image parts weigh the same)."""
        with torch.no_grad():
            tpf, timf = self.teacher["point_encoder"](points), self.teacher["image_encoder"](images)
        return (2.0 - F.cosine_similarity(pf, tpf, dim=-1).mean() - F.cosine_similarity(imf, timf, dim=1).mean()) / 2.0

    def rank_loss(self, samples, points, pf, imf, rng) -> torch.Tensor:
        """softplus(20 (margin - (score(truth) - score(perturbed)))) / 20, averaged over `rank_poses`
        perturbations per sample, with score = `state.alignment` (differentiable in both
        embeddings). A perturbation shifts the camera 0.3-3 m along its own x or z axis and, half
        of the time, turns it about its own y axis by 2-30 deg either way; a `rank_far` share of
        them is wide instead (30-180 deg about map z through the camera centre, a ground shift of
        up to `rank_far_shift_m` in any direction). With `rank_hard`, each sample's
        `hard_negatives` join them."""
        from .state import alignment
        cfg, dev = self.cfg, self.device
        b = len(samples)
        moved = [self.rank_perturbations(s.truth, rng) for s in samples]
        k = torch.as_tensor(np.stack([s.intrinsics for s in samples]), dtype=torch.float32, device=dev)
        if cfg.rank_hard > 0:
            for i, s in enumerate(samples):
                moved[i] += self.hard_negatives(s.truth, points[i], k[i], pf[i], imf[i], rng)
        margin = [[cfg.rank_margin] * len(m) for m in moved]
        if cfg.rank_near_hard > 0:
            for i, s in enumerate(samples):
                near = self.near_negatives(s.truth, points[i], k[i], pf[i], imf[i], rng)
                moved[i] += near
                margin[i] += [cfg.rank_near_margin] * len(near)
        margin = torch.as_tensor(margin, dtype=torch.float32, device=dev)  # [B, P]
        p = len(moved[0])
        truth = torch.as_tensor(np.stack([s.truth for s in samples]), dtype=torch.float32, device=dev)
        moved = torch.as_tensor(np.stack([m for ms in moved for m in ms]), dtype=torch.float32, device=dev)
        rep = lambda t: t.repeat_interleave(p, dim=0)  # noqa: E731
        good = alignment(truth, points, k, pf, imf)  # [B]
        bad = alignment(moved, rep(points), rep(k), rep(pf), rep(imf)).view(b, p)
        return (F.softplus(20.0 * (margin - (good[:, None] - bad))) / 20.0).mean()

    def rank_perturbations(self, truth: np.ndarray, rng) -> list[np.ndarray]:
        """`rank_poses` camera_from_map poses [4, 4] near `truth` for the ranking term (its docstring)."""
        cfg = self.cfg
        camera_centre = g.invert(truth)[:3, 3]  # the pivot: a turn in place
        moved = []
        for _ in range(cfg.rank_poses):
            if cfg.rank_far > 0 and rng.random() < cfg.rank_far:
                yaw_deg = rng.uniform(30.0, 180.0) * rng.choice([-1.0, 1.0])
                heading, dist = rng.uniform(0.0, 2 * math.pi), rng.uniform(0.0, cfg.rank_far_shift_m)
                moved.append(g.apply_action(truth, camera_centre, yaw_deg, dist * math.cos(heading),
                                            dist * math.sin(heading), frame=g.MAP_Z))
                continue
            yaw_deg = rng.uniform(2.0, 30.0) * rng.choice([-1.0, 1.0]) * (rng.random() < 0.5)
            shift = np.zeros(3)
            shift[rng.choice([0, 2])] = rng.uniform(0.3, 3.0) * rng.choice([-1.0, 1.0])
            moved.append(g.apply_action(truth, camera_centre, yaw_deg, shift[0], shift[2]))
        return moved

    def protocol_poses(self, truth: np.ndarray, count: int, rng) -> list[np.ndarray]:
        """`count` camera_from_map poses [4, 4] drawn around `truth` by `geometry.protocol_pose`,
        none of them registered (protocol A: within 10 deg / 5 m; such draws are drawn again)."""
        poses = []
        while len(poses) < count:
            pose = g.protocol_pose(truth, rng)
            if not g.registered(pose, truth):
                poses.append(pose)
        return poses

    def near_poses(self, truth: np.ndarray, count: int, rng) -> list[np.ndarray]:
        """`count` camera_from_map poses [4, 4] about `truth` as `cmr.diagnose`'s peak grid turns
        and shifts it: a turn uniform within +-`NEAR_TURN_DEG` about the camera centre (map z),
        then a ground shift (right and forward of the turned heading) uniform over the ring 1 to
        `NEAR_SHIFT_M` m."""
        centre = g.invert(truth)[:3, 3]
        poses = []
        for _ in range(count):
            yaw = rng.uniform(-NEAR_TURN_DEG, NEAR_TURN_DEG)
            r = math.sqrt(rng.uniform(1.0, NEAR_SHIFT_M ** 2))
            a = rng.uniform(0.0, 2 * math.pi)
            turned = g.apply_action(truth, centre, yaw, 0.0, 0.0, frame=g.MAP_Z)
            poses.append(g.apply_action(turned, centre, 0.0, r * math.cos(a), r * math.sin(a), frame=g.MAP_Z))
        return poses

    def hard_negatives(self, truth, points, k, pf, imf, rng) -> list[np.ndarray]:
        """The `rank_hard` best-scoring (`state.alignment`, no gradient) of `rank_hard_pool`
        `protocol_poses` of one sample (points [N, 3], k [4], pf [N, C], imf [C, H, W]), scored on
        `rank_hard_points` of its points (drawn after the pool) when that is set and fewer than all."""
        pool = self.protocol_poses(truth, self.cfg.rank_hard_pool, rng)
        points, pf = points_subset(points, pf, self.cfg.rank_hard_points, rng)
        return self.best_scoring(pool, self.cfg.rank_hard, points, k, pf, imf)

    def near_negatives(self, truth, points, k, pf, imf, rng) -> list[np.ndarray]:
        """The `rank_near_hard` best-scoring of `rank_near_pool` `near_poses` of one sample, scored
        on `rank_near_points` of its points (drawn after the pool) when that is set and fewer than all."""
        pool = self.near_poses(truth, self.cfg.rank_near_pool, rng)
        points, pf = points_subset(points, pf, self.cfg.rank_near_points, rng)
        return self.best_scoring(pool, self.cfg.rank_near_hard, points, k, pf, imf)

    @torch.no_grad()
    def best_scoring(self, pool, count, points, k, pf, imf) -> list[np.ndarray]:
        """The `count` poses of `pool` that score highest by `state.alignment`, no gradient."""
        from .state import alignment
        n = len(pool)
        poses = torch.as_tensor(np.stack(pool), dtype=torch.float32, device=self.device)
        score = alignment(poses, points.expand(n, *points.shape), k.expand(n, *k.shape),
                          pf.expand(n, *pf.shape), imf.expand(n, *imf.shape))
        return [pool[j] for j in torch.topk(score, min(count, n)).indices.tolist()]

    def embed_param_groups(self) -> list[dict]:
        """Stage 1's parameters; a pretrained backbone's in a group of their own whose learning rate
        is `backbone_lr_scale` times the schedule's (its `lr_scale`, kept in the optimiser's state)."""
        stage1 = [self.models[k] for k in ("point_encoder", "image_encoder", "frustum_head")]
        backbone = self.models["image_encoder"].backbone_parameters() if self.cfg.image_backbone != "scratch" else []
        ids = {id(p) for p in backbone}
        rest = [p for m in stage1 for p in m.parameters() if id(p) not in ids]
        groups = [dict(params=rest, lr_scale=1.0)]
        if backbone:
            groups.append(dict(params=backbone, lr_scale=self.cfg.backbone_lr_scale))
        return groups

    def embed_train_mode(self) -> None:
        """The stage-1 modules in training mode; with `embed_frozen_bn`, their BatchNorm layers
        stay in evaluation mode."""
        for k in ("point_encoder", "image_encoder", "frustum_head"):
            self.models[k].train()
            if self.cfg.embed_frozen_bn:
                for m in self.models[k].modules():
                    if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                        m.eval()

    def train_embed(self, deadline: float) -> None:
        cfg = self.cfg
        self.embed_train_mode()
        started = time.time()
        while self.embed_step < cfg.embed_steps and time.time() < deadline:
            if cfg.embed_seconds > 0 and time.time() - started >= cfg.embed_seconds:
                # Time budget spent: stage 1 ends here (config.json records the steps done).
                self.cfg = cfg = dataclasses.replace(cfg, embed_steps=self.embed_step)
                atomic_write_bytes(self.dir / "config.json", (json.dumps(dataclasses.asdict(cfg), indent=2) + "\n").encode())
                print(f"stage 1 time budget spent after {self.embed_step} steps", flush=True)
                break
            t0 = time.time()
            samples = self.samples(1, self.embed_step, cfg.embed_batch, cfg.embed_points)
            loss, stats = self.embed_losses(samples)
            progress = None
            if cfg.embed_seconds > 0:
                progress = self.stage_progress(self.embed_step, cfg.embed_steps, started, cfg.embed_seconds)
            lr = self.embed_lr(self.embed_step, progress)
            for group in self.opt_embed.param_groups:
                group["lr"] = lr * group.get("lr_scale", 1.0)
            self.opt_embed.zero_grad()
            loss.backward()
            if cfg.embed_grad_clip > 0:
                torch.nn.utils.clip_grad_norm_([p for grp in self.opt_embed.param_groups for p in grp["params"]],
                                               cfg.embed_grad_clip)
            self.opt_embed.step()
            self.embed_step += 1
            if self.embed_step % cfg.log_every == 0 or self.embed_step == 1:
                rec = dict(stage="embed", step=self.embed_step, loss=loss.item(), lr=lr, **stats,
                           samples_per_s=cfg.embed_batch / (time.time() - t0), time=time.time())
                self.log(rec)
                print(json.dumps(rec), flush=True)
            if self.embed_step % cfg.checkpoint_every == 0:
                self.save("last.pt")
            if cfg.keep_embed_every and self.embed_step % cfg.keep_embed_every == 0:
                self.keep(f"embed_{self.embed_step:06d}.pt")
            if cfg.embed_eval_every and (self.embed_step % cfg.embed_eval_every == 0 or self.embed_step == cfg.embed_steps):
                self.validate_embeddings()
                self.embed_train_mode()
        self.save("last.pt")

    def validate_embeddings(self) -> dict:
        from .evaluate import evaluate_embeddings
        if not self.val_frames:
            return {}
        result = evaluate_embeddings(self.models, self.val_frames, num_points=self.cfg.embed_points, device=self.device)
        rec = dict(stage="embed_val", step=self.embed_step, time=time.time(), **result)
        self.log(rec)
        print(json.dumps(rec), flush=True)
        return rec

    # -- stage 2 -----------------------------------------------------------------------------
    def agent_update(self, eps, traj, ppo_weight: float) -> dict:
        cfg, agent = self.cfg, self.models["agent"]
        steps, b = traj.actions.shape[:2]
        adv, ret = gae(traj.rewards, traj.values, cfg.gamma, cfg.gae_lambda)
        adv = (adv - adv.mean()) / (adv.std() + 1e-6)
        flat = [(t, i) for t in range(steps) for i in range(b)]
        rng = np.random.default_rng([cfg.seed, 7, self.agent_iter])
        totals = dict(bc=0.0, policy=0.0, value=0.0, entropy=0.0, bc_accuracy=0.0)
        updates = 0
        agent.train()
        for _ in range(cfg.update_epochs):
            order = rng.permutation(len(flat))
            for start in range(0, len(order), cfg.minibatch):
                batch = [flat[j] for j in order[start:start + cfg.minibatch]]
                rows = [i for _, i in batch]
                if traj.states is not None:
                    s2 = torch.stack([traj.states[t][0][i] for t, i in batch])
                    s3 = torch.stack([traj.states[t][1][i] for t, i in batch])
                else:
                    s2, s3 = eps.state([traj.poses[t][i] for t, i in batch], rows)
                    s2 = agent.correlate(s2)
                logits, value = agent.decide(s2, s3)
                dev = logits.device
                expert = torch.as_tensor(np.stack([traj.experts[t, i] for t, i in batch]), device=dev)
                bc = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), expert.reshape(-1))
                dist = torch.distributions.Categorical(logits=logits)
                acts = torch.as_tensor(np.stack([traj.actions[t, i] for t, i in batch]), device=dev)
                logp = dist.log_prob(acts).sum(-1)
                old = torch.as_tensor([traj.log_probs[t, i] for t, i in batch], device=dev)
                a = torch.as_tensor([adv[t, i] for t, i in batch], device=dev)
                ratio = torch.exp(logp - old)
                policy = -torch.min(ratio * a, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * a).mean()
                r = torch.as_tensor([ret[t, i] for t, i in batch], device=dev)
                value_loss = F.mse_loss(value[:, 0], r)
                entropy = dist.entropy().sum(-1).mean()
                loss = bc + cfg.value_weight * value_loss + ppo_weight * (policy - cfg.entropy_weight * entropy)
                self.opt_agent.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(agent.parameters(), 5.0)
                self.opt_agent.step()
                updates += 1
                totals["bc"] += bc.item()
                totals["policy"] += policy.item()
                totals["value"] += value_loss.item()
                totals["entropy"] += entropy.item()
                totals["bc_accuracy"] += (logits.argmax(-1) == expert).float().mean().item()
        agent.eval()
        return {k: v / max(updates, 1) for k, v in totals.items()}

    def train_agent(self, deadline: float) -> None:
        cfg = self.cfg
        for k in ("point_encoder", "image_encoder", "frustum_head"):
            self.models[k].eval()
        agent = self.models["agent"]
        # The pool is rebuilt deterministically on resume (seeded by iteration), then rolls.
        pool = embed_many(self.models, self.samples(4, self.agent_iter, cfg.pool_size, cfg.num_points), self.device,
                          action_frame=cfg.action_frame)
        degrade_image_features(pool, cfg.image_noise_p, cfg.image_noise_max, np.random.default_rng([cfg.seed, 6, self.agent_iter]))
        started = time.time()
        while self.agent_iter < cfg.agent_iters and time.time() < deadline:
            if cfg.agent_seconds > 0 and time.time() - started >= cfg.agent_seconds:
                print(f"stage 2 time budget spent after {self.agent_iter} iterations", flush=True)
                break
            t0 = time.time()
            it = self.agent_iter
            fresh = [(it * cfg.pool_refresh + j) % cfg.pool_size for j in range(cfg.pool_refresh)]
            new = embed(self.models, self.samples(2, it, cfg.pool_refresh, cfg.num_points), self.device, cfg.action_frame)
            degrade_image_features(new, cfg.image_noise_p, cfg.image_noise_max, np.random.default_rng([cfg.seed, 7, it]))
            pool.replace(fresh, new)
            rows = sorted(set(fresh) | set(np.random.default_rng([cfg.seed, 5, it]).choice(
                cfg.pool_size, cfg.agent_envs - len(fresh), replace=False).tolist()))
            eps = pool.subset(rows)
            frac = self.stage_progress(it, cfg.agent_iters, started, cfg.agent_seconds)
            lr = cfg.agent_lr_min + 0.5 * (cfg.agent_lr - cfg.agent_lr_min) * (1 + math.cos(math.pi * frac))
            for group in self.opt_agent.param_groups:
                group["lr"] = lr
            mix = cfg.expert_mix_start * max(0.0, 1.0 - it / max(cfg.expert_mix_iters, 1))
            ppo_weight = cfg.ppo_weight if it >= cfg.bc_only_iters else 0.0
            rng = np.random.default_rng([cfg.seed, 3, it])
            gen = torch.Generator(device=self.device).manual_seed(cfg.seed * 100003 + it)
            agent.eval()
            traj = rollout(agent, eps, cfg.rollout_steps, "sample", mix, rng, gen, keep_states=True)
            stats = self.agent_update(eps, traj, ppo_weight)
            self.update_agent_ema()
            self.agent_iter += 1
            if self.agent_iter % cfg.log_every == 0 or self.agent_iter == 1:
                rec = dict(stage="agent", step=self.agent_iter, lr=lr, expert_mix=mix, ppo_weight=ppo_weight,
                           reward=float(traj.rewards.mean()), **stats,
                           samples_per_s=cfg.agent_envs / (time.time() - t0), time=time.time())
                self.log(rec)
                print(json.dumps(rec), flush=True)
            if self.agent_iter % cfg.checkpoint_every == 0:
                self.save("last.pt")
            if cfg.keep_agent_every and self.agent_iter % cfg.keep_agent_every == 0:
                self.keep(f"agent_{self.agent_iter:05d}.pt")
            if cfg.eval_every and self.agent_iter % cfg.eval_every == 0:
                self.validate()
        self.save("last.pt")

    @torch.no_grad()
    def update_agent_ema(self) -> None:
        if self.agent_ema is None:
            return
        live = self.models["agent"].state_dict()
        for name, avg in self.agent_ema.state_dict().items():
            if avg.dtype.is_floating_point:
                avg.lerp_(live[name], 1.0 - self.cfg.agent_ema)
            else:
                avg.copy_(live[name])

    def shipped_models(self) -> dict:
        """The graphs validation, best.pt and export see: the averaged agent when there is one."""
        return self.models if self.agent_ema is None else {**self.models, "agent": self.agent_ema}

    def validate(self) -> dict:
        from .evaluate import evaluate
        if not self.val_frames:
            return {}
        result = evaluate(self.shipped_models(), self.val_frames, num_points=self.cfg.num_points, device=self.device,
                          action_frame=self.cfg.action_frame)
        final = result["agent"][-1]
        rec = dict(stage="val", step=self.agent_iter, embed_step=self.embed_step, frames=len(self.val_frames), time=time.time(),
                   final=final, expert_final=result["expert"][-1], frustum=result["frustum"],
                   match_accuracy=result["match_accuracy"])
        self.log(rec)
        print(json.dumps(rec), flush=True)
        atomic_write_bytes(self.dir / f"val_{self.agent_iter:06d}.json", (json.dumps(result, indent=2) + "\n").encode())
        score = (final["rr"], -final["rte_m"])
        if self.best is None or score > tuple(self.best):
            self.best = list(score)
            self.save("best.pt")
            atomic_write_bytes(self.dir / "best_val.json", (json.dumps(result, indent=2) + "\n").encode())
        return result


def adopt_init_architecture(cfg: Config, given: set[str]) -> Config:
    """With `init_from`, the architecture (`norm`, `image_edges`, `image_backbone`, `point_encoder`) is the checkpoint's unless given
    explicitly: a fine-tune of `models/` (v3: BatchNorm, v7: GroupNorm) needs no flag for it. A
    value given that contradicts the checkpoint stops the run in `Run._init_from`."""
    if not cfg.init_from or not Path(cfg.init_from).exists():
        return cfg
    state = torch.load(cfg.init_from, map_location="cpu", weights_only=False)
    arch = {k: v for k, v in arch_of(state.get("meta", {}).get("config", {})).items() if k not in given}
    return dataclasses.replace(cfg, **arch)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="comma-separated KITTI-layout roots or sequence directories")
    ap.add_argument("--val-data", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="override any Config field")
    ap.add_argument("--hours", type=float, default=1e9, help="stop (after a checkpoint) after this long")
    args = ap.parse_args(argv)
    cfg = Config()
    overrides = list(args.set)
    for key, value in (("data", args.data), ("val_data", args.val_data), ("out", args.out)):
        if value is not None:
            overrides.append(f"{key}={value}")
    cfg = Config.from_overrides(cfg, overrides)
    cfg = adopt_init_architecture(cfg, {o.split("=", 1)[0] for o in overrides})
    if not cfg.data:
        raise SystemExit("--data is required")
    torch.set_num_threads(cfg.threads)
    run = Run(cfg)
    atomic_write_bytes(run.dir / "config.json", (json.dumps(dataclasses.asdict(cfg), indent=2) + "\n").encode())
    deadline = time.time() + args.hours * 3600
    run.train_embed(deadline)
    cfg = run.cfg  # a stage-1 time budget lowers embed_steps to the steps done
    if run.embed_step >= cfg.embed_steps:
        run.train_agent(deadline)
        if cfg.eval_every and run.agent_iter % cfg.eval_every:
            run.validate()
    run.close()


if __name__ == "__main__":
    main()
