#!/usr/bin/env bash
# One whole training run on a machine with one large GPU, 16 cores, PyTorch installed and no
# network, in about 9 minutes: world-v2 data from the release binary, both stages with the
# transfer recipe (heavy photometric + zoom + LiDAR augmentation, GroupNorm encoders, warm-up +
# cosine stage 1) in the map_z action frame, a quarter of the maps cut like a fleet region's crop
# (virtual_scan_p: seen from beside the camera, so no model can take the scan's centre for the
# camera; its cost on the GPU machine is not yet measured: 0.14 s per such sample on one CPU
# core, a loader worker's job), a brief evaluation, ONNX + manifest.
#
#   OUT=/path/to/out scripts/train-gpu.sh             # the real run (GPU machine)
#   TINY=1 PYTHON=.venv/bin/python OUT=/tmp/gpu-tiny scripts/train-gpu.sh   # a few minutes on 2 CPU cores
#
# Environment (all optional except on the GPU machine, where OUT is given):
#   OUT            results: models/ (4 ONNX + manifest.json), eval.json, log.jsonl, config.json,
#                  training_curves.png, checkpoint/last.pt, logs/ (default: runs/gpu-out); and
#                  models-int8/ (the same set with int8 Conv layers) when $PYTHON has onnxruntime
#   PYTHON         the interpreter with torch, numpy, pillow, onnx (default python3; nothing is
#                  installed, the network is never used)
#   CMR_AGENT_BIN  the release binary (default target/release/cmr-agent, carried along)
#   TINY=1         shrink everything (data, steps, points) so it ends in minutes on a CPU
#   JOBS           parallel data-generation processes (default: nproc)
#   WORK           scratch for the generated data (default: a fresh /tmp directory; not in OUT)
#   EMBED_S, AGENT_S  wall-time budgets of the two stages in seconds (default 170 each)
#   EXTRA_SET      more `key=value` Config overrides, applied last (e.g. "image_edges=true embed_batch=16")
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
OUT=${OUT:-$ROOT/runs/gpu-out}
PYTHON=${PYTHON:-python3}
BIN=${CMR_AGENT_BIN:-$ROOT/target/release/cmr-agent}
TINY=${TINY:-0}
JOBS=${JOBS:-$(nproc)}
WORK=${WORK:-$(mktemp -d /tmp/cmr-train-gpu.XXXXXX)}
case "$OUT" in /*) ;; *) OUT=$PWD/$OUT ;; esac
case "$BIN" in /*) ;; *) BIN=$PWD/$BIN ;; esac
case "$PYTHON" in */*) case "$PYTHON" in /*) ;; *) PYTHON=$PWD/$PYTHON ;; esac ;; esac
mkdir -p "$OUT/logs" "$WORK"
T0=$(date +%s)
stamp() { echo "[train-gpu +$(( $(date +%s) - T0 ))s] $*" | tee -a "$OUT/logs/timeline.txt"; }

[ -x "$BIN" ] || { echo "no release binary at $BIN (set CMR_AGENT_BIN)" >&2; exit 2; }
"$PYTHON" -c "import torch, numpy, PIL, onnx" || { echo "$PYTHON lacks torch/numpy/pillow/onnx" >&2; exit 2; }
"$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')" | tee "$OUT/logs/python.txt"

if [ "$TINY" = 1 ]; then
  SEQS=1; FRAMES=4; VAL_FRAMES=4; BLOCKS=2; VAL_RIGS="kitti"
  EMBED_S=${EMBED_S:-60}; AGENT_S=${AGENT_S:-60}
  TRAIN_SET="embed_steps=6 embed_points=4096 embed_batch=2 embed_warmup=2 agent_iters=4 agent_envs=4
    pool_size=6 pool_refresh=2 num_points=8192 bc_only_iters=2 expert_mix_iters=2 minibatch=20
    threads=2 loader_workers=1 eval_frames=2 embed_eval_every=3 log_every=1 checkpoint_every=50"
  EVAL_FRAMES=2
else
  SEQS=3; FRAMES=30; VAL_FRAMES=8; BLOCKS=$JOBS; VAL_RIGS="kitti nuscenes wide vlp16 os128 random"
  EMBED_S=${EMBED_S:-170}; AGENT_S=${AGENT_S:-170}
  TRAIN_SET="embed_steps=20000 embed_points=16384 embed_batch=8 embed_warmup=100 agent_iters=1500
    agent_envs=16 pool_size=64 pool_refresh=4 bc_only_iters=500 expert_mix_iters=300 update_epochs=1
    threads=4 loader_workers=$(( JOBS > 4 ? JOBS - 4 : 1 )) eval_frames=24 embed_eval_every=500
    log_every=10 checkpoint_every=100"
  EVAL_FRAMES=36
fi

# -- 1. data: one synth process per block, blocks cycle through the rigs; the last block is the
#    classic street with the classic look (today's sets); validation: every rig, test style.
stamp "generating data into $WORK ($BLOCKS training blocks x $SEQS x $FRAMES frames)"
RIGS=(kitti nuscenes wide vlp16 os128 random random random)
pids=()
for k in $(seq 0 $(( BLOCKS - 1 ))); do
  rig=${RIGS[$(( k % ${#RIGS[@]} ))]}
  extra=(--rig "$rig")
  if [ "$BLOCKS" -gt 2 ] && [ "$k" -eq $(( BLOCKS - 1 )) ]; then extra=(--world classic --look classic); fi
  nice -n 5 "$BIN" synth --out "$WORK/train/b$k" "${extra[@]}" --sequences "$SEQS" --frames "$FRAMES" \
    --seed $(( 40000 + 100 * k )) --image-scale 0.5 --quiet > "$OUT/logs/synth-b$k.log" 2>&1 &
  pids+=($!)
done
for rig in $VAL_RIGS; do
  nice -n 5 "$BIN" synth --out "$WORK/val/$rig" --rig "$rig" --sequences 1 --frames "$VAL_FRAMES" \
    --seed 95000 --style test --image-scale 0.5 --quiet > "$OUT/logs/synth-val-$rig.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
TRAIN_DATA=$(ls -d "$WORK"/train/b* | paste -sd, -)
# The Python readers take a root whose children are sequences: flatten the validation blocks.
mkdir -p "$WORK/val-flat"
for d in "$WORK"/val/*/*/; do ln -sfn "$d" "$WORK/val-flat/$(basename "$(dirname "$d")")-$(basename "$d")"; done
stamp "data done: $(ls -d "$WORK"/train/b*/* | wc -l) training sequences, $(ls "$WORK"/val-flat | wc -l) validation"

# -- 2. train both stages (one process; each stage ends at its time budget)
RUN="$WORK/run"
stamp "training (stage budgets ${EMBED_S}s + ${AGENT_S}s)"
cd "$ROOT/training"
# shellcheck disable=SC2086
"$PYTHON" -m cmr.train --data "$TRAIN_DATA" --val-data "$WORK/val-flat" --out "$RUN" --set \
  action_frame=map_z norm=group embed_schedule=cosine embed_lr=2e-3 embed_lr_min=2e-5 embed_grad_clip=5 \
  photometric=heavy scale_max=1.5 lidar_aug=true map_window=5 map_scans=3 map_window_p=0 virtual_scan_p=0.25 \
  eval_every=0 \
  embed_seconds="$EMBED_S" agent_seconds="$AGENT_S" $TRAIN_SET ${EXTRA_SET:-} > "$OUT/logs/train.log" 2>&1
cp "$RUN/log.jsonl" "$RUN/config.json" "$OUT/"
mkdir -p "$OUT/checkpoint" && cp "$RUN/last.pt" "$OUT/checkpoint/last.pt"
stamp "training done: $(grep -c '"stage": "embed"' "$RUN/log.jsonl") stage-1 and $(grep -c '"stage": "agent"' "$RUN/log.jsonl") stage-2 log records"

# -- 3. brief evaluation (Python evaluator, the paper's protocol, single start) and export
"$PYTHON" -m cmr.evaluate --checkpoint "$RUN/last.pt" --data "$WORK/val-flat" --frames "$EVAL_FRAMES" \
  --out "$OUT/eval.json" > "$OUT/logs/eval.log" 2>&1
stamp "evaluated: $("$PYTHON" -c "import json,sys; r=json.load(open(sys.argv[1])); f=r['agent'][-1]; print('RR', round(f['rr'],3), 'RTE', round(f['rte_m'],3), 'match', round(r['match_accuracy'],4), 'frustum', {k: round(v,3) for k,v in r['frustum'].items()})" "$OUT/eval.json")"
"$PYTHON" -m cmr.export --checkpoint "$RUN/last.pt" --out "$OUT/models" --validation "$OUT/eval.json" \
  > "$OUT/logs/export.log" 2>&1
"$PYTHON" -m cmr.plots "$RUN" --out "$OUT/training_curves.png" > "$OUT/logs/plots.log" 2>&1 || stamp "plots skipped (see logs/plots.log)"
stamp "exported to $OUT/models"
# The served form: the agent's Conv layers in int8 (7-bit weights), calibrated on the validation frames (judge both sets with
# `cmr-agent eval` before shipping either; docs: training/README.md, "Quantised graphs").
if "$PYTHON" -m cmr.quantize --models "$OUT/models" --calibration "$WORK/val-flat" --out "$OUT/models-int8" \
    > "$OUT/logs/quantize.log" 2>&1; then
  stamp "quantised to $OUT/models-int8"
else
  stamp "quantisation failed (see logs/quantize.log)"
fi

# -- 4. the server loads them. ONNX Runtime's library: $ORT_DYLIB_PATH, else runtime/ next to the
#    binary's checkout (the binary's own search), else the one inside $PYTHON's onnxruntime wheel.
cd "$ROOT"
if [ -z "${ORT_DYLIB_PATH:-}" ] && [ ! -e "$ROOT/runtime/libonnxruntime.so" ]; then
  lib=$("$PYTHON" -c "import glob, os, onnxruntime as o; print((sorted(glob.glob(os.path.join(os.path.dirname(o.__file__), 'capi', 'libonnxruntime.so*'))) or [''])[0])" 2>/dev/null || true)
  [ -n "$lib" ] && export ORT_DYLIB_PATH=$lib
fi
if "$BIN" localize --models "$OUT/models" --map maps/demo.bin --request examples/localize-demo.json \
    > "$OUT/localize-demo.json" 2> "$OUT/logs/localize.log"; then
  stamp "server localize on the demo: ok ($OUT/localize-demo.json)"
else
  stamp "server localize failed (see logs/localize.log); the models are still in $OUT/models"
fi
if [ -d "$OUT/models-int8" ] && "$BIN" localize --models "$OUT/models-int8" --map maps/demo.bin \
    --request examples/localize-demo.json > "$OUT/localize-demo-int8.json" 2>> "$OUT/logs/localize.log"; then
  stamp "server localize on the demo with the int8 set: ok"
fi
[ -n "${KEEP_WORK:-}" ] || rm -rf "$WORK"
stamp "done"
