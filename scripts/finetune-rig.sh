#!/usr/bin/env bash
# Fine-tune the shipped model on one rig's own real frames and measure it on that rig's frames the
# fine-tune never saw (issue 29): the commands of training/README.md's "Fine-tuning on your own
# drive", run on a real drive instead of a generated one.
#
#   scripts/finetune-rig.sh data    # link the train and held-out drives (no frame is copied)
#   scripts/finetune-rig.sh train   # import the shipped set, stage 1 then stage 2 (niced, foreground)
#   scripts/finetune-rig.sh eval    # export; `cmr-agent eval` of shipped and fine-tuned on the same cases
#
# RIG picks the drives from ../shared/real-train (`cmr.real_split`'s rigs.json); both held-out
# drives are `cmr.real_split`'s validation drives, which no shipped model since v7 has read:
#   ddad (default)  train on scene_02 (sequences 082-090, 9 frames), held out scene_01 (079-081, 3 frames)
#   aimotive        train on keyframes 33643-33679 (091-103, 13 frames), held out 33682-33691 (104-107, 4)
# Environment: RIG, or TRAIN_SEQS / HELD_SEQS (sequence ids, space-separated) for your own drive,
# NAME (default ft-$RIG), WORK (default ~/.cache/cmr-agent/runs/$NAME), MODELS (the set to start
# from, default models/), EMBED_STEPS (600), AGENT_ITERS (300), NICE (5), REAL (default
# ../shared/real-train), CASES (default docs/eval/$NAME-held-perturbations.json; drawn on first use).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
RIG=${RIG:-ddad}
case $RIG in
  ddad) train_default=$(seq -f %03g 82 90); held_default=$(seq -f %03g 79 81) ;;
  aimotive) train_default=$(seq -f %03g 91 103); held_default=$(seq -f %03g 104 107) ;;
  *) train_default=""; held_default="" ;;
esac
NAME=${NAME:-ft-$RIG}
WORK=${WORK:-$HOME/.cache/cmr-agent/runs/$NAME}
MODELS=$(readlink -f "${MODELS:-$ROOT/models}")
REAL=$(readlink -f "${REAL:-$ROOT/../shared/real-train}")
TRAIN_SEQS=${TRAIN_SEQS:-$train_default}
HELD_SEQS=${HELD_SEQS:-$held_default}
[ -n "$TRAIN_SEQS" ] && [ -n "$HELD_SEQS" ] || { echo "RIG=$RIG is not a preset: set TRAIN_SEQS and HELD_SEQS" >&2; exit 2; }
EMBED_STEPS=${EMBED_STEPS:-600}
AGENT_ITERS=${AGENT_ITERS:-300}
NICE=${NICE:-5}
CASES=${CASES:-$ROOT/docs/eval/$NAME-held-perturbations.json}
PY=$ROOT/.venv/bin/python
BIN=$ROOT/target/release/cmr-agent

data() {
  mkdir -p "$WORK/train" "$WORK/held"
  for s in $TRAIN_SEQS; do ln -sfn "$REAL/sequences/$s" "$WORK/train/$s"; done
  for s in $HELD_SEQS; do ln -sfn "$REAL/sequences/$s" "$WORK/held/$s"; done
  echo "train: $(ls "$WORK/train" | wc -l) frames, held out: $(ls "$WORK/held" | wc -l) frames, in $WORK"
}

# The shipped set's weights (`cmr.import_onnx`: what a user of `models/` has), then stage 1 at a
# fifth of the shipped run's learning rate with its ranking term and transfer augmentations, then
# stage 2 at a sixth of its rate with fleet-like starts for a third of the episodes, in the
# shipped action frame and normalisation. The held-out drive is the validation set only (training's
# own figure); training never reads it.
train() {
  cd "$ROOT/training"
  [ -f "$WORK/shipped.pt" ] || "$PY" -m cmr.import_onnx "$MODELS" --out "$WORK/shipped.pt"
  # the architecture follows the checkpoint (`cmr.train`); the action frame is read from it too
  local frame
  frame=$("$PY" -c "import torch,sys; print(torch.load(sys.argv[1], map_location='cpu', weights_only=False)['meta']['config'].get('action_frame', 'camera_y'))" "$WORK/shipped.pt")
  nice -n "$NICE" "$PY" -m cmr.train --data "$WORK/train" --val-data "$WORK/held" --out "$WORK/run" --set \
    action_frame="$frame" init_from="$WORK/shipped.pt" embed_steps="$EMBED_STEPS" embed_lr=2e-4 backbone_lr_scale=0.1 \
    embed_schedule=cosine embed_warmup=50 embed_lr_min=1e-5 embed_grad_clip=5 rank_weight=2 rank_poses=8 rank_far=0.5 \
    photometric=heavy scale_max=1.5 lidar_aug=true embed_eval_every=300 \
    agent_iters="$AGENT_ITERS" agent_lr=5e-5 agent_lr_min=1e-5 agent_ema=0.995 bc_only_iters=0 \
    expert_mix_start=0.2 expert_mix_iters=100 near_start_p=0.3 pool_size=24 update_epochs=2 eval_every=100 eval_frames=12 \
    checkpoint_every=50 log_every=20 threads=2 loader_workers=1
}

# Exported and quantised as the shipped set is (the agent's Conv layers in int8, calibrated on the rig's training
# frames), then both sets on the same frozen cases, 8 per frame, in both regimes (the paper's
# protocol and a fleet-grade prior): the held-out drive (committed cases files) and, for contrast,
# the training drive. The fine-tuned set is the run's last checkpoint: picking the best validation
# iteration would choose on the held-out drive it is measured on.
evaluate() {
  cd "$ROOT/training"
  "$PY" -m cmr.export --checkpoint "$WORK/run/last.pt" --out "$WORK/models-float" >/dev/null
  "$PY" -m cmr.quantize --models "$WORK/models-float" --calibration "$WORK/train" --out "$WORK/models" >/dev/null
  cd "$ROOT"
  for regime in protocol fleet; do
    for part in held train; do
      case $part-$regime in
        held-protocol) cases=$CASES ;;
        held-fleet) cases=${CASES%-perturbations.json}-fleet-perturbations.json ;;
        *) cases=$WORK/$part-$regime-perturbations.json ;;
      esac
      for m in shipped:"$MODELS" tuned:"$WORK/models"; do
        nice -n "$NICE" "$BIN" eval --data "$WORK/$part" --models "${m#*:}" --out "$WORK/eval-${m%%:*}-$part-$regime" \
          --perturbations "$cases" --cases-per-frame 8 --priors $regime --seed 33 --quiet >/dev/null
        echo "== ${m%%:*} model, $part frames, $regime priors ($(basename "$cases"))"
        grep -A5 '^## Table 1:' "$WORK/eval-${m%%:*}-$part-$regime/tables.md" | tail -4
      done
    done
  done
}

case "${1:-}" in
  data|train) "$1" ;;
  eval) evaluate ;;
  *) sed -n 2,15p "$0"; exit 2 ;;
esac
