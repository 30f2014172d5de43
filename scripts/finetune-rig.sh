#!/usr/bin/env bash
# Fine-tune the shipped model on one rig's own real frames and measure it on that rig's frames the
# fine-tune never saw (issue 29): the commands of training/README.md's "Fine-tuning on your own
# drive", run on a real drive instead of a generated one.
#
#   scripts/finetune-rig.sh data    # link the train and held-out drives (no frame is copied)
#   scripts/finetune-rig.sh train   # import the shipped set, stage 1 then stage 2 (niced, foreground)
#   scripts/finetune-rig.sh eval    # export; `cmr-agent eval` of shipped and fine-tuned on the same cases
#
# Default: nuScenes, train on scene-0523 (27 frames), held out scene-0916 (28 frames), both from
# ../shared/real-train (sequences 022-048 and 049-076, see `cmr.real_split`'s rigs.json).
# Environment: TRAIN_SEQS / HELD_SEQS (sequence ids, space-separated), NAME (default ft-nuscenes),
# WORK (default ~/.cache/cmr-agent/runs/$NAME), EMBED_STEPS (1000), AGENT_ITERS (200), NICE (5),
# REAL (default ../shared/real-train), CASES (default docs/eval/$NAME-held-perturbations.json).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
NAME=${NAME:-ft-nuscenes}
WORK=${WORK:-$HOME/.cache/cmr-agent/runs/$NAME}
REAL=$(readlink -f "${REAL:-$ROOT/../shared/real-train}")
TRAIN_SEQS=${TRAIN_SEQS:-$(seq -f %03g 22 48)}
HELD_SEQS=${HELD_SEQS:-$(seq -f %03g 49 76)}
EMBED_STEPS=${EMBED_STEPS:-1000}
AGENT_ITERS=${AGENT_ITERS:-200}
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

# Stage 1 with the shipped BatchNorm statistics frozen and the ranking term (the alignment score
# must rank the true pose above perturbed ones), then stage 2 in the shipped action frame. The
# held-out drive is the validation set; training never reads it.
train() {
  cd "$ROOT/training"
  [ -f "$WORK/shipped.pt" ] || "$PY" -m cmr.import_onnx ../models --out "$WORK/shipped.pt"
  nice -n "$NICE" "$PY" -m cmr.train --data "$WORK/train" --val-data "$WORK/held" --out "$WORK/run" --set \
    init_from="$WORK/shipped.pt" embed_frozen_bn=true embed_steps="$EMBED_STEPS" embed_lr=5e-4 \
    embed_schedule=cosine embed_warmup=100 embed_lr_min=2e-5 embed_grad_clip=5 rank_weight=2 rank_poses=8 \
    photometric=heavy lidar_aug=true embed_eval_every=250 \
    agent_iters="$AGENT_ITERS" agent_lr=2e-4 agent_lr_min=2e-5 agent_ema=0.995 bc_only_iters=100 \
    expert_mix_start=0.3 expert_mix_iters=100 pool_size=24 update_epochs=2 eval_every=50 eval_frames=12 \
    checkpoint_every=25 log_every=20 threads=2 loader_workers=1
}

# Exported and quantised as the shipped set is (int8 Conv layers, calibrated on the rig's training
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
      for m in shipped:models tuned:"$WORK/models"; do
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
