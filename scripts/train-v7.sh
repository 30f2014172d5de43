#!/usr/bin/env bash
# Run v7 (issue 29): both stages on the mix of world-v2 + classic synthetic data and the real
# frames of ../shared/real-train, on this 2-core CPU, across sessions.
#
#   scripts/train-v7.sh data     # makes the data under $DATA (idempotent; synth ~10 min of CPU)
#   scripts/train-v7.sh start    # starts or resumes the run, niced, in the background
#   scripts/train-v7.sh save     # copies the run's last.pt to training/checkpoints/v7.pt (commit it)
#   scripts/train-v7.sh status   # the run's pid, its last log records
#   RUN=~/.cache/cmr-agent/runs/v8f scripts/train-v7.sh start-v8f
#                                # run v8f (issue 29): stage 2 again from the shipped model (v7),
#                                # encoders kept, half the episodes from fleet-like starts, one
#                                # thread; `save` and `status` with the same RUN (saves v8f.pt)
#   RUN=~/.cache/cmr-agent/runs/v9e scripts/train-v7.sh start-v9e
#                                # run v9e (issue 29): stage 1 continued from the shipped model's
#                                # float weights (v7's iteration-1,500 export, imported), agent
#                                # kept, the ranking term doubled, real frames six times in the draw
#   RUN=~/.cache/cmr-agent/runs/v10 scripts/train-v7.sh start-v10
#                                # run v10 (issue 29): v7's whole recipe (both stages, from
#                                # scratch) with half the samples mirrored; across sessions
#   RUN=~/.cache/cmr-agent/runs/v11 scripts/train-v7.sh start-v11
#                                # run v11 (issue 29): v7's recipe with the image encoder on an
#                                # ImageNet-pretrained EfficientNet-Lite0 backbone; across sessions
#   RUN=~/.cache/cmr-agent/runs/v12 scripts/train-v7.sh start-v12
#                                # run v12 (issue 29): the shipped v11 trained on with half the
#                                # samples mirrored, both stages; across sessions
#   RUN=~/.cache/cmr-agent/runs/v13 scripts/train-v7.sh start-v13
#                                # run v13 (issue 29): v11's encoders trained on with hard
#                                # negatives in the ranking term, stage 1 only (v11's agent kept)
#   RUN=~/.cache/cmr-agent/runs/v14 scripts/train-v7.sh start-v14
#                                # run v14 (issue 29): v11 with the image encoder's stride-32
#                                # stages added, stage 1 only (v11's agent kept)
#   RUN=~/.cache/cmr-agent/runs/v14a scripts/train-v7.sh start-v14a
#                                # run v14a (issue 29): stage 2 of v11's agent on v14's encoders
#   RUN=~/.cache/cmr-agent/runs/v15 scripts/train-v7.sh start-v15
#                                # run v15 (issue 29): v11 with a second, 0.4 m grid in the point
#                                # encoder, both stages (v11's agent trained on)
#   RUN=~/.cache/cmr-agent/runs/v16 scripts/train-v7.sh start-v16
#                                # run v16 (issue 29): v11's agent trained on with half the rollout
#                                # pool's image features made noisy (weak evidence), encoders kept
#   RUN=~/.cache/cmr-agent/runs/v17 scripts/train-v7.sh start-v17
#                                # run v17 (issue 29): the shipped v11 with its image backbone
#                                # swapped for ImageNet EfficientNet-Lite1's, both stages
#   RUN=~/.cache/cmr-agent/runs/v18 scripts/train-v7.sh start-v18
#                                # run v18 (issue 29): v11's whole recipe on EfficientNet-Lite1's
#                                # ImageNet backbone, encoders from scratch, samples at one focal
#                                # length (cmr.data.FOCAL_RANGE_PX); across sessions
#   RUN=~/.cache/cmr-agent/runs/v19 scripts/train-v7.sh start-v19
#                                # run v19 (issue 29): v18's agent at iteration 2,000 trained on
#                                # with half the episodes from fleet-like starts, encoders kept
#   RUN=~/.cache/cmr-agent/runs/v9m scripts/train-v7.sh start-v9m
#                                # run v9m: like v9e but v7's data mix and ranking term, with half
#                                # the samples mirrored (image and map together), 4,000 steps
#   RUN=~/.cache/cmr-agent/runs/v9a scripts/train-v7.sh start-v9a
#                                # run v9a: stage 2 continued on v9e's finished encoders (the
#                                # agent from v7's, as v9e kept it), 600 iterations, one thread
#   RUN=~/.cache/cmr-agent/runs/v34 scripts/train-v7.sh start-v34
#                                # run v34 (issue 29): v11 whose point encoder also reads each
#                                # point's intensity rank, stage 1 only (v11's agent kept)
#   RUN=~/.cache/cmr-agent/runs/v35 scripts/train-v7.sh start-v35
#                                # run v35 (issue 29): v34's recipe without intensity on every
#                                # real-train frame (the split's held-out drives too)
#   RUN=~/.cache/cmr-agent/runs/v26 scripts/train-v7.sh start-v26
#                                # run v26: v11's encoders on with near hard negatives in the
#                                # ranking term (4,000 steps), then 1,000 agent iterations
#   RUN=~/.cache/cmr-agent/runs/v27 scripts/train-v7.sh start-v27
#                                # run v27: v26 with the near negatives the best 8 of 256 poses
#                                # (scored on 4,096 points) instead of the best 4 of 32
#   RUN=~/.cache/cmr-agent/runs/v28 scripts/train-v7.sh start-v28
#                                # run v28: v27 with the near negatives' margin 0.05 and the
#                                # ranking term's weight 4
#   RUN=~/.cache/cmr-agent/runs/v29 scripts/train-v7.sh start-v29
#                                # run v29: v28's stage 1 carried on 4,000 steps from its end with
#                                # the margin 0.1, then 1,000 agent iterations
#   RUN=~/.cache/cmr-agent/runs/v30 scripts/train-v7.sh start-v30
#                                # run v30: v28's stage 1 carried on 4,000 steps from its end with
#                                # the best 8 of 256 far (protocol-like) poses as hard negatives too
#   RUN=~/.cache/cmr-agent/runs/v32 scripts/train-v7.sh start-v32
#                                # run v32: v30's stage 1 carried on 2,000 steps from its end with
#                                # feature distillation towards v11's encoders (stage 1 only)
#   scripts/train-v7.sh judge CHECKPOINT NAME [SET...]
#                                # exports and quantises CHECKPOINT into $RUN/judge/NAME (a model set
#                                # folder, e.g. models/, is linked there as it is), then runs
#                                # `cmr-agent eval` (the server's search) on each SET: rtv-protocol,
#                                # rtv-fleet, rtv-fleet2 (a second fleet sample of the same drives,
#                                # seed 3106), dev-protocol, dev-fleet, the four 16-per-frame files
#                                # rtv-protocol16, rtv-fleet16, dev-protocol16, dev-fleet16, run v32's
#                                # fresh-rtv-protocol, fresh-rtv-fleet, fresh-dev-protocol,
#                                # fresh-dev-fleet, fresh-synth-test, fresh-own-synth, fresh-v2-val, synth-test,
#                                # v2-val, own-synth, and fused (tests/fleet_maps.rs's two 42-case
#                                # files on the candidate) (default: rtv-protocol synth-test);
#                                # EVAL_FLAGS adds eval flags (e.g. "--prior-bound 30,5") and TAG a
#                                # suffix; QUANTIZE_GRAPHS names the int8 graphs (cmr.quantize's
#                                # default: the agent alone, the image encoder float)
#
# Resuming: `start` resumes from $RUN/last.pt; when that is missing (a fresh machine) or behind
# the committed training/checkpoints/v7.pt (fewer steps), the committed file is copied there first, byte
# for byte, so a run resumes from either place with the same state (sampling is seeded by step).
# Environment: DATA (default ~/.cache/cmr-agent/data), RUN (default ~/.cache/cmr-agent/runs/v7),
# NICE (default 5), CMR_AGENT_BIN (default target/release/cmr-agent).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
DATA=${DATA:-$HOME/.cache/cmr-agent/data}
RUN=${RUN:-$HOME/.cache/cmr-agent/runs/v7}
NICE=${NICE:-5}
BIN=${CMR_AGENT_BIN:-$ROOT/target/release/cmr-agent}
PY=$ROOT/.venv/bin/python
REAL=${REAL:-$ROOT/../shared/real-train}
SAVED=$ROOT/training/checkpoints/$(basename "$RUN").pt

# world v2 (six rigs' blocks + one classic block) and the real split; validation mixes both
data() {
  mkdir -p "$DATA/v7/train" "$DATA/v7/val-mix"
  local k rig
  for kr in 0:kitti 1:nuscenes 2:wide 3:vlp16 4:os128 5:random; do
    k=${kr%%:*}; rig=${kr#*:}
    [ -f "$DATA/v7/train/b$k/.done" ] || { nice -n "$NICE" "$BIN" synth --out "$DATA/v7/train/b$k" --rig "$rig" \
      --sequences 3 --frames 30 --seed $((40000 + 100 * k)) --image-scale 0.5 --quiet && touch "$DATA/v7/train/b$k/.done"; }
  done
  [ -f "$DATA/v7/train/b6/.done" ] || { nice -n "$NICE" "$BIN" synth --out "$DATA/v7/train/b6" --world classic \
    --look classic --sequences 3 --frames 30 --seed 40600 --image-scale 0.5 --quiet && touch "$DATA/v7/train/b6/.done"; }
  for rig in kitti nuscenes random; do
    [ -f "$DATA/v7/val/$rig/.done" ] || { nice -n "$NICE" "$BIN" synth --out "$DATA/v7/val/$rig" --rig "$rig" \
      --sequences 1 --frames 8 --seed 95000 --style test --image-scale 0.5 --quiet && touch "$DATA/v7/val/$rig/.done"; }
    ln -sfn "$DATA/v7/val/$rig/00" "$DATA/v7/val-mix/synth-$rig"
  done
  # the judge's synthetic sets: classic synth-test (docs/evaluation.md), world-v2 validation as one
  # folder, and frames of the generator's default worlds and rig (own-synth)
  [ -f "$DATA/synth-test/.done" ] || { nice -n "$NICE" "$BIN" synth --out "$DATA/synth-test" --sequences 4 --frames 50 \
    --seed 5000 --style test --world classic --look classic --quiet && touch "$DATA/synth-test/.done"; }
  [ -f "$DATA/own-synth/.done" ] || { nice -n "$NICE" "$BIN" synth --out "$DATA/own-synth" --sequences 4 --frames 10 \
    --seed 8800 --quiet && touch "$DATA/own-synth/.done"; }
  mkdir -p "$DATA/v2-val-flat"
  for rig in kitti nuscenes random; do ln -sfn "$DATA/v7/val/$rig/00" "$DATA/v2-val-flat/$rig-00"; done
  (cd "$ROOT/training" && "$PY" -m cmr.real_split --src "$REAL" --out "$DATA/real-split")
  [ -f "$HOME/.cache/cmr-agent/runs/v3-import.pt" ] || (cd "$ROOT/training" && mkdir -p "$HOME/.cache/cmr-agent/runs" &&
    "$PY" -m cmr.import_onnx ../models --out "$HOME/.cache/cmr-agent/runs/v3-import.pt")
  for s in "$DATA"/real-split/val/*; do ln -sfn "$(readlink -f "$s")" "$DATA/v7/val-mix/real-$(basename "$s")"; done
}

# The real training frames count three times in the draw (97 of ~730 frames otherwise).
train_roots() {
  local r=$DATA/real-split/train
  echo "$(ls -d "$DATA"/v7/train/b* | paste -sd, -),$r,$r,$r"
}

# steps done by a checkpoint (stage 1 steps + stage 2 iterations): which copy is further along
progress() {
  "$PY" -c "import torch,sys; c=torch.load(sys.argv[1], map_location='cpu', weights_only=False); print(c['embed_step'] + c['agent_iter'])" "$1"
}

# The committed checkpoint replaces the run directory's last.pt when that is missing or behind it
# (byte for byte, so a run resumes from either place with the same state).
resume_saved() {
  if [ -f "$SAVED" ] && { [ ! -f "$RUN/last.pt" ] || [ "$(progress "$SAVED")" -gt "$(progress "$RUN/last.pt")" ]; }; then
    cp "$SAVED" "$RUN/last.pt"
    echo "resuming from the committed $SAVED"
  fi
}

# Whether a run's start file `$1` has to be made: it is missing and the run starts afresh (a run
# that resumes, from its last.pt or its committed checkpoint, already holds what it took from it).
needs_init() {
  [ ! -f "$1" ] && [ ! -f "$RUN/last.pt" ] && [ ! -f "$SAVED" ]
}

# The shipped model's float weights as a checkpoint (v7's iteration-1,500 export, the ONNX files
# `models/` was quantised from), made once: where the runs after v7 start from. A run that resumes
# (its last.pt or committed checkpoint exists) already holds what it took from them, so the file is
# only made for a fresh start; a machine that lost the float export cannot start one afresh.
v7_float() {
  local init=$HOME/.cache/cmr-agent/runs/v7-float-import.pt
  if needs_init "$init"; then
    (cd "$ROOT/training" && "$PY" -m cmr.import_onnx "$HOME/.cache/cmr-agent/runs/v7/judge/s2k15/float" --out "$init" >&2)
  fi
  echo "$init"
}

# Settings every run since v7 shares: the action frame, the encoders' normalisation, the transfer
# augmentations and a quarter of the maps cut like a fleet region's crop.
COMMON=(action_frame=map_z norm=group photometric=heavy scale_max=1.5 lidar_aug=true
  map_window=5 map_scans=3 map_window_p=0 virtual_scan_p=0.25)
# v7's stage 1 and stage 2.
V7_STAGE1=(embed_schedule=cosine embed_lr=1e-3 embed_warmup=200 embed_lr_min=2e-5 embed_grad_clip=5
  rank_weight=2 rank_poses=8 rank_far=0.5 embed_steps=30000 embed_eval_every=2000)
V7_STAGE2=(agent_iters=3000 agent_lr=3e-4 agent_lr_min=2e-5 agent_ema=0.995 bc_only_iters=300
  expert_mix_start=0.3 expert_mix_iters=300 pool_size=48 update_epochs=2 near_start_p=0.3
  eval_every=250 eval_frames=36 checkpoint_every=100 log_every=20 threads=2 loader_workers=1)

# launch TRAIN_ROOTS SETTING...: starts or resumes $RUN (after `resume_saved`) with `cmr.train`,
# niced, in the background, on TRAIN_ROOTS with val-mix for validation and COMMON + SETTING...
# (a later setting of the same key wins).
launch() {
  local roots=$1; shift
  mkdir -p "$RUN"
  resume_saved
  cd "$ROOT/training"
  nohup nice -n "$NICE" "$PY" -m cmr.train --data "$roots" --val-data "$DATA/v7/val-mix" --out "$RUN" \
    --set "${COMMON[@]}" "$@" >> "$RUN/stdout.log" 2>&1 &
  echo $! > "$RUN/pid"
  echo "started pid $(cat "$RUN/pid"), log $RUN/stdout.log"
}

# Run v7: both stages, stage 2 from the v3 agent's weights.
start() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" \
    init_agent_from="$HOME/.cache/cmr-agent/runs/v3-import.pt"
}

# Run v8f: the shipped agent trained on from the shipped model's own weights (cmr.import_onnx of
# models/, made once into $RUN/../v7-import.pt), stage 1 skipped, with half the episodes starting
# within 30 deg / 5 m of the truth (the fleet regime) at a lower learning rate.
start_v8f() {
  local init=$RUN/../v7-import.pt
  [ -f "$init" ] || (cd "$ROOT/training" && "$PY" -m cmr.import_onnx ../models --out "$init")
  launch "$(train_roots)" "${V7_STAGE2[@]}" init_from="$init" embed_steps=0 agent_iters=1500 agent_lr=1e-4 \
    agent_lr_min=1e-5 bc_only_iters=0 expert_mix_start=0.2 near_start_p=0.5 checkpoint_every=50 threads=1 loader_workers=0
}

# Run v9e: stage 1 only, from the shipped model's float weights (the agent in them kept as it is),
# the ranking term's weight and margin doubled, the real training frames six times in the draw
# (about half of all samples), one thread.
start_v9e() {
  local r=$DATA/real-split/train
  launch "$(ls -d "$DATA"/v7/train/b* | paste -sd, -),$r,$r,$r,$r,$r,$r" "${V7_STAGE1[@]}" init_from="$(v7_float)" \
    embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 rank_weight=4 rank_margin=0.1 embed_steps=6000 \
    embed_eval_every=1000 agent_iters=0 checkpoint_every=100 log_every=20 threads=1 loader_workers=0
}

# Run v9m: stage 1 continued from the shipped float weights (as v9e) with v7's own data mix and
# ranking term, half of the samples mirrored left to right (image and map together:
# data.mirror_sample), learning rate 1e-4 -> 1e-5 over 4,000 steps, one thread; a copy of every
# 1,000th step in $RUN/snap/ (the shipping rule's candidates).
start_v9m() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" init_from="$(v7_float)" mirror_p=0.5 embed_lr=1e-4 \
    embed_warmup=100 embed_lr_min=1e-5 embed_steps=4000 embed_eval_every=1000 keep_embed_every=1000 agent_iters=0 \
    checkpoint_every=100 log_every=20 threads=1 loader_workers=0
}

# Run v9a: the agent (v7's, kept by v9e) trained on for 600 iterations on v9e's final encoders,
# frozen; v7's stage-2 recipe at a tenth of its learning rate; a copy of iteration 300 in
# $RUN/snap/.
start_v9a() {
  launch "$(train_roots)" "${V7_STAGE2[@]}" init_from="$RUN/../v9e/last.pt" embed_steps=0 agent_iters=600 \
    agent_lr=1e-4 agent_lr_min=1e-5 bc_only_iters=0 expert_mix_start=0.2 eval_every=300 checkpoint_every=50 \
    keep_agent_every=300 threads=1 loader_workers=0
}

# Run v10: v7's recipe (both stages from scratch) with half the samples mirrored (mirror_p=0.5)
# and stage 2 starting from the shipped agent (v7's, map_z) instead of v3's; a copy of every
# 500th stage-2 iteration in $RUN/snap/ (the shipping rule's candidates). `save` at every stop.
start_v10() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" mirror_p=0.5 init_agent_from="$(v7_float)" \
    keep_agent_every=500
}

# Run v11: v7's recipe (both stages from scratch, stage 2 from the shipped agent like v10) with the
# image encoder on an ImageNet-pretrained EfficientNet-Lite0 (models.LiteImageEncoder; its
# backbone at a tenth of the learning rate, its BatchNorm statistics kept); a copy of every 500th
# stage-2 iteration in $RUN/snap/. `save` at every stop.
start_v11() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 \
    backbone_lr_scale=0.1 init_agent_from="$(v7_float)" keep_agent_every=500
}

# The shipped v11's checkpoint (stage-2 iteration 2,000, kept in git at commit e0ba91f), copied
# once to runs/v11-shipped.pt: where runs v12 and v13 start from. Like v7_float, only made for a
# fresh start (a run that resumes already holds what it took from it).
v11_shipped() {
  local init=$HOME/.cache/cmr-agent/runs/v11-shipped.pt
  if needs_init "$init" || [ "${1:-}" = always ]; then
    from_git e0ba91f:training/checkpoints/v11.pt "$init"
  fi
  echo "$init"
}

# from_git REV:PATH FILE: a file of git's history copied to FILE once (kept when it is there).
from_git() {
  [ -f "$2" ] && return 0
  mkdir -p "$(dirname "$2")"
  git -C "$ROOT" show "$1" > "$2.tmp" && mv "$2.tmp" "$2"
}

# Run v12: the shipped v11 (stage-2 iteration 2,000; its checkpoint, kept in git at commit e0ba91f
# and copied once to runs/v11-shipped.pt) trained on with half the samples mirrored (v10's
# augmentation, which v11 did not have): 8,000 more stage-1 steps at a fifth of v7's learning
# rate, then 1,500 stage-2 iterations from v11's agent at a third of its rate; a copy of every
# 2,000th stage-1 step and every 500th stage-2 iteration in $RUN/snap/. `save` at every stop.
start_v12() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 \
    backbone_lr_scale=0.1 init_from="$(v11_shipped)" mirror_p=0.5 embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 \
    embed_steps=8000 keep_embed_every=2000 agent_iters=1500 agent_lr=1e-4 agent_lr_min=1e-5 bc_only_iters=0 \
    expert_mix_start=0.2 keep_agent_every=500
}

# Run v13: the shipped v11's encoders trained on with hard negatives in the ranking term (of 32
# protocol-like poses per sample, the 2 that score best join its 8 perturbations: the wrong poses
# the search answers with), 6,000 stage-1 steps at a fifth of v7's learning rate; no stage 2: the
# checkpoints carry v11's agent (run v12 measured its stage-1 encoders with v11's agent at 134 of
# 192, level, and a continued stage 2 below it). A copy of every 1,500th step in $RUN/snap/.
start_v13() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 \
    backbone_lr_scale=0.1 init_from="$(v11_shipped)" embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 \
    embed_steps=6000 keep_embed_every=1500 embed_eval_every=1500 rank_hard_pool=32 rank_hard=2 agent_iters=0
}

# Run v14: the shipped v11 with a deeper image encoder: EfficientNet-Lite0's stride-32 stages
# (ImageNet weights, at the backbone's tenth of the rate) join the decoder through a 1x1 lateral
# layer whose input weights start at zero, so step 0 computes exactly v11
# (`LiteImageEncoder.load_shallow`); 6,000 stage-1 steps at a fifth of v7's learning rate, no
# stage 2 (v11's agent, as in v13). A copy of every 1,500th step in $RUN/snap/.
start_v14() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0_s32 \
    backbone_lr_scale=0.1 init_from="$(v11_shipped)" embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 \
    embed_steps=6000 keep_embed_every=1500 embed_eval_every=1500 agent_iters=0
}

# Run v14a: stage 2 on v14's encoders. v14's stage 1 (step 6,000) judged better than v11 on the
# held-out drives by cmr.diagnose (truth beats all protocol-like poses in 6 of 12 frames against 5)
# but registered fewer cases with v11's agent; so v11's agent (which v14's checkpoint carries) is
# trained on those encoders, stage 1 skipped: 1,500 iterations at v12's stage-2 settings, a copy of
# every 500th in $RUN/snap/. The encoders' optimiser never steps, so a checkpoint is ~24 MB and
# `save` commits it whole. The start copies v14's snapshot once to runs/v14-e06000.pt (a resume
# needs neither: it holds what it took).
start_v14a() {
  local init=$HOME/.cache/cmr-agent/runs/v14-e06000.pt
  if needs_init "$init"; then
    cp "$HOME/.cache/cmr-agent/runs/v14/snap/embed_006000.pt" "$init.tmp" && mv "$init.tmp" "$init"
  fi
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0_s32 \
    init_from="$init" embed_steps=0 agent_iters=1500 agent_lr=1e-4 agent_lr_min=1e-5 bc_only_iters=0 \
    expert_mix_start=0.2 keep_agent_every=500
}

# Run v15: the shipped v11 with a finer point encoder: a second BEV grid of 0.4 m cells (two 3x3
# layers, gathered back to each point beside the 0.8 m context) whose way into the head starts at
# zero, so step 0 computes exactly v11 (`PointEncoder.load_coarse`). The point encoder runs once
# per map region, so the request's FLOPs do not change. 6,000 stage-1 steps at v14's settings,
# then 1,500 stage-2 iterations of v11's agent on the final encoders at v14a's; a copy of every
# 1,500th step and every 500th iteration in $RUN/snap/. `save` at every stop.
start_v15() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 point_encoder=pillars_fine \
    backbone_lr_scale=0.1 init_from="$(v11_shipped)" embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 \
    embed_steps=6000 keep_embed_every=1500 embed_eval_every=1500 agent_iters=1500 agent_lr=1e-4 agent_lr_min=1e-5 \
    bc_only_iters=0 expert_mix_start=0.2 keep_agent_every=500
}

# Run v16: the shipped v11's agent trained on, its encoders kept, with half of the rollout pool's
# image features made noisy (image_noise_p / image_noise_max: evidence as weak as real frames of
# unseen drives give), 1,000 iterations at a twentieth of v7's stage-2 rate; a copy every 250th.
start_v16() {
  launch "$(train_roots)" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 init_from="$(v11_shipped)" \
    embed_steps=0 agent_iters=1000 agent_lr=5e-5 agent_lr_min=1e-5 bc_only_iters=0 expert_mix_start=0.2 \
    image_noise_p=0.5 image_noise_max=0.35 checkpoint_every=50 keep_agent_every=250
}

# Run v17: the shipped v11 with its image encoder's backbone swapped for EfficientNet-Lite1's
# ImageNet weights (15 blocks to stride 16 instead of Lite0's 11, the same widths), its decoder,
# point encoder, frustum head and agent kept (`LiteImageEncoder.load_decoder`): 10,000 stage-1
# steps at half of v7's rate, then v7's stage 2 (v11's recipe) for 1,500 iterations from v11's
# agent; a copy of every 2,000th step and every 500th iteration in $RUN/snap/. `save` at every stop.
start_v17() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite1 \
    backbone_lr_scale=0.1 init_from="$(v11_shipped)" embed_lr=5e-4 embed_warmup=300 embed_lr_min=2e-5 \
    embed_steps=10000 keep_embed_every=2000 embed_eval_every=2000 agent_iters=1500 keep_agent_every=500
}

# Run v18: v11's whole recipe (both stages, the encoders from scratch: 30,000 stage-1 steps, 3,000
# stage-2 iterations) with EfficientNet-Lite1's ImageNet backbone in place of Lite0's and every sample
# made at one focal length (cmr.data.FOCAL_RANGE_PX, the make_sample default since 2026-12-05), the agent
# from the shipped v11's (v7's float export, v11's start, is gone with an earlier machine); a copy of
# every 5,000th step and every 500th iteration in $RUN/snap/. Across sessions: `save` at every stop.
start_v18() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite1 \
    backbone_lr_scale=0.1 init_agent_from="$(v11_shipped)" keep_embed_every=5000 keep_agent_every=500
}

# Run v19: v18's agent (stage-2 iteration 2,000, the candidate that passed clause 1 under the
# polish's wide pass) trained on with its encoders kept, half the episodes from fleet-like starts,
# learning rate 1e-4 -> 1e-5 over 1,000 iterations; a copy every 250 in $RUN/snap/.
start_v19() {
  launch "$(train_roots)" "${V7_STAGE2[@]}" init_from="$RUN/../v18/snap/agent_02000.pt" embed_steps=0 \
    agent_iters=1000 agent_lr=1e-4 agent_lr_min=1e-5 bc_only_iters=0 expert_mix_start=0.2 near_start_p=0.5 \
    keep_agent_every=250 checkpoint_every=50
}

# v19's stage-2 recipe as v20 runs it on v11's agent: half the episodes from fleet-like starts,
# 1e-4 -> 1e-5 over 1,000 iterations, no BC-only phase, a copy every 250 in $RUN/snap/.
V20_STAGE2=(agent_iters=1000 agent_lr=1e-4 agent_lr_min=1e-5 bc_only_iters=0 expert_mix_start=0.2 near_start_p=0.5
  keep_agent_every=250 checkpoint_every=50)

# Run v20: V20_STAGE2 on the shipped v11 (its encoders and agent; runs/v11-shipped.pt), stage 1
# skipped. SETTING... after these (a later one wins).
start_v20() {
  launch "$(train_roots)" "${V7_STAGE2[@]}" init_from="$(v11_shipped)" embed_steps=0 "${V20_STAGE2[@]}" "$@"
}

# Run v21: v20 with half the samples' maps cut from a drive region as the server cuts them
# (virtual_scan_p 0.5 instead of COMMON's 0.25), for the fused-region cases v20 lost.
start_v21() {
  start_v20 virtual_scan_p=0.5 "$@"
}

# Run v22: v21 with its fleet-like starts turned at most 10 deg instead of 30 (the shift still
# within 5 m), so that half the episodes start with the heading nearly right and the position off:
# the translation the fused-region cases end short of.
start_v22() {
  start_v21 near_start_yaw_deg=10
}

# Run v24: v11's encoders trained on (stage 1, 6,000 steps at v14's rate) with three quarters of
# the maps cut from a drive region as the server cuts them (virtual_scan_p 0.75: no density centre
# at the camera), then v20's stage 2 on them (v11's agent, 1,000 iterations).
start_v24() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 backbone_lr_scale=0.1 \
    init_from="$(v11_shipped)" embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 embed_steps=6000 keep_embed_every=1500 \
    embed_eval_every=1500 "${V20_STAGE2[@]}" virtual_scan_p=0.75 "$@"
}

# Run v26: v24's shape (v11's encoders trained on with stage 1 from the shipped weights, then
# V20_STAGE2's agent stage) with near hard negatives in the ranking term (cmr.train's
# `rank_near_*`: the best-scoring of 32 poses turned within 8 deg and shifted 1-5 m join each
# sample's negatives, margin 0.02) and COMMON's map cuts. SETTING... after these (a later one wins).
start_v26() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" image_backbone=efficientnet_lite0 backbone_lr_scale=0.1 \
    init_from="$(v11_shipped)" embed_lr=2e-4 embed_warmup=100 embed_lr_min=1e-5 embed_steps=4000 keep_embed_every=1000 \
    embed_eval_every=1000 rank_near_pool=32 rank_near_hard=4 rank_near_margin=0.02 "${V20_STAGE2[@]}" "$@"
}

# Run v27: v26 with a pool eight times larger (the best 8 of 256 near poses, ranked on 4,096 of
# the sample's points to keep a step at about 0.8 s), so that the near negatives are the poses
# that beat the truth rather than a random few of them.
start_v27() {
  start_v26 rank_near_pool=256 rank_near_hard=8 rank_near_points=4096 "$@"
}

# Run v28: v27 with the near negatives' margin 0.05 (v27 0.02) and the ranking term at weight 4
# (V7_STAGE1's 2): the truth must beat the best near poses by four to six times the score's gain
# at its peak on held-out real frames, and the term weighs twice as much against the circle loss.
start_v28() {
  start_v27 rank_near_margin=0.05 rank_weight=4 "$@"
}

# Run v29: v28's stage 1 carried on from its end (v28's snap/embed_004000.pt, which holds v11's
# agent) for 4,000 more steps with the near negatives' margin 0.1 (v28 0.05), then V20_STAGE2.
start_v29() {
  start_v28 init_from="$HOME/.cache/cmr-agent/runs/v28/snap/embed_004000.pt" rank_near_margin=0.1 "$@"
}

# Run v30: v28's stage 1 carried on from its end as v29, v28's margin kept, with hard negatives
# far from the truth as well: the best 8 of 256 protocol-like poses (any heading, within 10 m,
# none registered), scored on 4,096 of the sample's points; then V20_STAGE2.
start_v30() {
  start_v28 init_from="$HOME/.cache/cmr-agent/runs/v28/snap/embed_004000.pt" rank_hard_pool=256 rank_hard=8 \
    rank_hard_points=4096 "$@"
}

# v30's committed checkpoint (git 7d5afbe, agent iteration 300; stage 2 trains the agent alone, so
# its encoders are those of v30's snap/embed_004000.pt), copied once to runs/v30-iter300.pt. Only
# made for a fresh start, like v11_shipped.
v30_committed() {
  local init=$HOME/.cache/cmr-agent/runs/v30-iter300.pt
  if needs_init "$init"; then
    from_git 7d5afbe:training/checkpoints/v30.pt "$init"
  fi
  echo "$init"
}

# Run v32: v30's stage-1 end (its encoders, v11's agent) carried on for 2,000 steps with v30's
# ranking terms (near and far hard negatives) and feature distillation towards v11's encoders (the
# teacher, read again at every resume, so runs/v11-shipped.pt is made whenever it is missing), so
# that the encoders keep what v11 knew of synthetic frames; stage 1 only.
start_v32() {
  local teacher
  teacher=$(v11_shipped always)
  start_v28 init_from="$(v30_committed)" init_agent_from="$teacher" rank_hard_pool=256 rank_hard=8 \
    rank_hard_points=4096 distill_from="$teacher" distill_weight=10 embed_steps=2000 embed_lr=1e-4 \
    keep_embed_every=500 embed_eval_every=1000 agent_iters=0 "$@"
}

# Run v34: the shipped v11 whose point encoder also reads each point's intensity, as its rank among
# the N input points (`data.intensity_rank`; "pillars_intensity", the new column's weights starting
# at zero, so step 0 computes exactly v11), 3,000 stage-1 steps at v13's settings with a tenth of the
# samples given no intensity (rank 0.5), v11's agent kept. A copy of every 500th step in $RUN/snap/.
V34_STAGE1=(image_backbone=efficientnet_lite0 backbone_lr_scale=0.1 embed_lr=3e-4 embed_warmup=100 embed_lr_min=1e-5
  embed_steps=3000 keep_embed_every=500 embed_eval_every=1000 rank_hard_pool=32 rank_hard=2 agent_iters=0)
start_v34() {
  launch "$(train_roots)" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" "${V34_STAGE1[@]}" point_encoder=pillars_intensity \
    intensity_drop_p=0.1 init_from="$(v11_shipped)" "$@"
}

# Run v35: v34's recipe without the intensity input (v13's stage-1 settings, 3,000 steps from the
# shipped v11, its agent kept) on every real frame of ../shared/real-train: the held-out drives of
# the split (real-split/val, five more drives of five rigs) join the training ones, both three times
# in the draw. The final fit once a recipe is settled; real-dev and synthetic frames judge it.
start_v35() {
  local r=$DATA/real-split/train v=$DATA/real-split/val
  launch "$(ls -d "$DATA"/v7/train/b* | paste -sd, -),$r,$r,$r,$v,$v,$v" "${V7_STAGE1[@]}" "${V7_STAGE2[@]}" \
    "${V34_STAGE1[@]}" init_from="$(v11_shipped)" "$@"
}

save() {
  mkdir -p "$(dirname "$SAVED")"
  cp "$RUN/last.pt" "$SAVED.tmp" && mv "$SAVED.tmp" "$SAVED"
  ls -l "$SAVED"
  "$PY" -c "import torch,sys; c=torch.load(sys.argv[1], map_location='cpu', weights_only=False); print('embed_step', c['embed_step'], 'agent_iter', c['agent_iter'])" "$SAVED"
}

# intensity_free ROOT: a copy of the KITTI-layout sequences under ROOT (made once, beside it, named
# ROOT-intensity0) whose scans have every intensity 0: a map without intensity, for models that read
# it (images, calibration and poses are links)
intensity_free() {
  local out=$1-intensity0 seq
  if [ ! -f "$out/.done" ]; then
    for seq in "$1"/*/; do
      seq=$(readlink -f "$seq")
      mkdir -p "$out/$(basename "$seq")/velodyne"
      for f in "$seq"/*; do [ "$(basename "$f")" = velodyne ] || ln -sfn "$f" "$out/$(basename "$seq")/"; done
      "$PY" -c "import numpy as np, sys, pathlib
for src in sorted(pathlib.Path(sys.argv[1]).glob('*.bin')):
    a = np.fromfile(src, np.float32).reshape(-1, 4); a[:, 3] = 0; a.tofile(pathlib.Path(sys.argv[2]) / src.name)" \
        "$seq/velodyne" "$out/$(basename "$seq")/velodyne"
    done
    touch "$out/.done"
  fi
  echo "$out"
}

# export + quantise a checkpoint like the shipped set, then `cmr-agent eval` on the named sets
# fresh_set NAME: a set of the files drawn for one judgement each, after its candidate existed and
# before anything was judged on them: fresh2-* for run v34, fresh3-* for run v35 (training/README.md),
# fresh4-* for the judge's views and fresh5-* for the judge's gate (docs/evaluation.md, "The judge's
# views in the server", "Reading the judge's views only when the starts disagree"). Set K of
# rtv-protocol, rtv-fleet, dev-protocol, dev-fleet, synth-test, own-synth, v2-val is seeded
# 4100 + 100 N + K (fresh3 has no rtv sets: run v35 trained on the held-out drives). Sets data, cases
# and draw (how the file is drawn on its first use); fails on a name it does not know.
fresh_set() {
  local n=${1%%-*} set=${1#*-} k per prefix priors=""
  n=${n#fresh}
  case $set in
    rtv-protocol) k=1 per=16 data=$DATA/real-split/val prefix=real-train-val ;;
    rtv-fleet) k=2 per=16 data=$DATA/real-split/val prefix=real-train-val-fleet priors="--priors fleet" ;;
    dev-protocol) k=3 per=16 data=$REAL/../real-dev prefix=real-dev ;;
    dev-fleet) k=4 per=16 data=$REAL/../real-dev prefix=real-dev-fleet priors="--priors fleet" ;;
    synth-test) k=5 per=1 data=$DATA/synth-test prefix=synth-test ;;
    own-synth) k=6 per=4 data=$DATA/own-synth prefix=own-synth ;;
    v2-val) k=7 per=4 data=$DATA/v2-val-flat prefix=v2-val ;;
    *) return 1 ;;
  esac
  if [ "$n" = 3 ] && [ "$k" -le 2 ]; then return 1; fi
  local seed=$((4100 + 100 * n + k))
  cases=docs/eval/$prefix-seed$seed-perturbations.json
  draw="--cases-per-frame $per --seed $seed${priors:+ $priors}"
}

judge() {
  local ckpt=$(readlink -f "$1") name=$2; shift 2
  local out=$RUN/judge/$name sets=("$@") tag=${TAG:-}
  [ ${#sets[@]} -gt 0 ] || sets=(rtv-protocol synth-test)
  mkdir -p "$out"
  if [ -f "$ckpt/manifest.json" ]; then
    [ -e "$out/models" ] || ln -s "$ckpt" "$out/models"  # a model set as it is (e.g. models/, the shipped one)
  elif [ ! -f "$out/models/manifest.json" ]; then
    (cd "$ROOT/training" && nice -n "$NICE" "$PY" -m cmr.export --checkpoint "$ckpt" --out "$out/float" &&
      nice -n "$NICE" "$PY" -m cmr.quantize --models "$out/float" --calibration "$DATA/v7/train/b0" "$DATA/real-split/train" \
        ${QUANTIZE_GRAPHS:+--graphs "$QUANTIZE_GRAPHS"} --out "$out/models") > "$out/export.log" 2>&1
  fi
  # CALIBRATOR_FROM=DIR: a candidate without a calibrator of its own gets DIR's (e.g. models/, when
  # no real frame it has not trained on is left to fit one; run v35), so its cases carry a verdict
  if [ -n "${CALIBRATOR_FROM:-}" ] && [ ! -L "$out/models" ]; then
    local from; from=$(readlink -f "$CALIBRATOR_FROM")
    (cd "$ROOT/training" && "$PY" -c "import json, sys; from pathlib import Path; from cmr.files import atomic_write_bytes
src, dst = (Path(a) / 'manifest.json' for a in sys.argv[1:])
doc = json.loads(dst.read_text())
if 'calibrator' not in doc:
    cal = json.loads(src.read_text())['calibrator']
    cal['provenance'] = dict(cal['provenance'], carried_from=str(src.resolve()))
    doc['calibrator'] = cal
    atomic_write_bytes(dst, (json.dumps(doc, indent=2) + '\\n').encode())" "$from" "$out/models")
  fi
  local set data cases draw
  for set in "${sets[@]}"; do
    draw=""  # how a set's case file is drawn on its first use (fresh2-*); an existing file is read
    case $set in
      rtv-protocol) data=$DATA/real-split/val; cases=docs/eval/real-train-val-perturbations.json ;;
      rtv-fleet) data=$DATA/real-split/val; cases=docs/eval/real-train-val-fleet-perturbations.json ;;
      rtv-fleet2) data=$DATA/real-split/val; cases=docs/eval/real-train-val-fleet-seed3106-perturbations.json ;;
      dev-protocol) data=$REAL/../real-dev; cases=docs/eval/real-dev-perturbations.json ;;
      dev-fleet) data=$REAL/../real-dev; cases=docs/eval/real-dev-fleet-perturbations.json ;;
      # 16 cases per frame, drawn 2026-12-07 (run v21's second judgement; training/README.md)
      rtv-protocol16) data=$DATA/real-split/val; cases=docs/eval/real-train-val-seed4101-perturbations.json ;;
      rtv-fleet16) data=$DATA/real-split/val; cases=docs/eval/real-train-val-fleet-seed4102-perturbations.json ;;
      dev-protocol16) data=$REAL/../real-dev; cases=docs/eval/real-dev-seed4103-perturbations.json ;;
      dev-fleet16) data=$REAL/../real-dev; cases=docs/eval/real-dev-fleet-seed4104-perturbations.json ;;
      # drawn 2026-12-07 14:19 UTC for runs v32 and v33, before any model was judged on them (training/README.md)
      fresh-rtv-protocol) data=$DATA/real-split/val; cases=docs/eval/real-train-val-seed4201-perturbations.json ;;
      fresh-rtv-fleet) data=$DATA/real-split/val; cases=docs/eval/real-train-val-fleet-seed4202-perturbations.json ;;
      fresh-dev-protocol) data=$REAL/../real-dev; cases=docs/eval/real-dev-seed4203-perturbations.json ;;
      fresh-dev-fleet) data=$REAL/../real-dev; cases=docs/eval/real-dev-fleet-seed4204-perturbations.json ;;
      fresh-synth-test) data=$DATA/synth-test; cases=docs/eval/synth-test-seed4205-perturbations.json ;;
      fresh-own-synth) data=$DATA/own-synth; cases=docs/eval/own-synth-seed4206-perturbations.json ;;
      fresh-v2-val) data=$DATA/v2-val-flat; cases=docs/eval/v2-val-seed4207-perturbations.json ;;
      # the -noint set reads run v34's held-out frames with every intensity 0 (`intensity_free`)
      fresh2-rtv-protocol-noint) data=$(intensity_free "$DATA/real-split/val"); cases=docs/eval/real-train-val-seed4301-perturbations.json ;;
      fresh[2-5]-*) fresh_set "$set" || { echo "unknown set $set" >&2; return 2; } ;;
      synth-test) data=$DATA/synth-test; cases=docs/eval/perturbations.json ;;
      v2-val) data=$DATA/v2-val-flat; cases=docs/eval/v2-val-perturbations.json ;;
      own-synth) data=$DATA/own-synth; cases=docs/eval/own-synth-perturbations.json ;;
      fused)  # tests/fleet_maps.rs, the region fused from a drive, 42 cases 5 m / 30 deg off, without
        # and with the bound stated: the candidate through the server (CMR_TEST_MODELS)
        (cd "$ROOT" && for t in "five_metre -- --ignored" "with_the_bound --"; do
          # shellcheck disable=SC2086
          CMR_TEST_MODELS=$out/models nice -n "$NICE" cargo test --release --test fleet_maps $t --nocapture 2>&1 || true  # a miss of its bar is a figure here
        done) > "$out/fused.log"
        printf '%-22s' fused; grep -h 'deg off.*RR' "$out/fused.log" | sed 's/, mean localize.*//' | tr '\n' ';'; echo
        continue ;;
      *) echo "unknown set $set" >&2; return 2 ;;
    esac
    # shellcheck disable=SC2086
    [ -f "$ROOT/$cases" ] && draw=""
    (cd "$ROOT" && nice -n "$NICE" "$BIN" eval --data "$data" --perturbations "$cases" --models "$out/models" $draw \
      --out "$out/$set$tag" --no-baseline --worst 0 --quiet ${EVAL_FLAGS:-}) > "$out/$set$tag.log" 2>&1
    printf '%-22s' "$set$tag"
    awk -F'|' '/^## Table 1:/{t=1; next} /^## /{t=0} t && $2 ~ /cmr-agent|no-op/ {printf " %s%s%%;", $2, $6}' "$out/$set$tag/tables.md"
    echo
  done
}

status() {
  [ -f "$RUN/pid" ] && ps -o pid,stat,etime,time,cmd -p "$(cat "$RUN/pid")" | cut -c1-120 || true
  tail -n 3 "$RUN/stdout.log" 2>/dev/null | cut -c1-400
}

case "${1:-}" in
  data|start|save|status) "$1" ;;
  start-v8f) start_v8f ;;
  start-v9e) start_v9e ;;
  start-v9a) start_v9a ;;
  start-v9m) start_v9m ;;
  start-v10) start_v10 ;;
  start-v11) start_v11 ;;
  start-v12) start_v12 ;;
  start-v13) start_v13 ;;
  start-v14) start_v14 ;;
  start-v14a) start_v14a ;;
  start-v15) start_v15 ;;
  start-v16) start_v16 ;;
  start-v17) start_v17 ;;
  start-v18) start_v18 ;;
  start-v19) start_v19 ;;
  start-v20) start_v20 ;;
  start-v21) start_v21 ;;
  start-v22) start_v22 ;;
  start-v24) start_v24 ;;
  start-v26) start_v26 ;;
  start-v27) start_v27 ;;
  start-v28) start_v28 ;;
  start-v29) start_v29 ;;
  start-v30) start_v30 ;;
  start-v32) start_v32 ;;
  start-v34) start_v34 ;;
  start-v35) start_v35 ;;
  judge) shift; judge "$@" ;;
  *) awk 'NR > 1 && /^#/ { print; next } NR > 1 { exit }' "$0"; exit 2 ;;
esac
