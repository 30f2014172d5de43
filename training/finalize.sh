#!/usr/bin/env bash
# Turn a run's checkpoint into the shipped model: evaluate on held-out frames, export the four
# graphs + manifest, measure the 2D state's alignment signal, time the graphs in ONNX Runtime, plot the curves, write models/MODEL_CARD.md.
# The background trainer (pid in <run>/pid) is paused meanwhile so the timings are not disturbed.
# The evaluation runs the multi-start search with HYPOTHESES starts (6th argument, default 4; 1 = single start).
#   bash finalize.sh runs/dev1 best.pt ../data/synth-test 40 "../data/synth-dev,../data/synth-train" [4]
set -euo pipefail
cd "$(dirname "$0")"
RUN=$1 CKPT=$2 TEST=$3 FRAMES=$4 TRAIN=$5 HYPOTHESES=${6:-4}
PY=../.venv/bin/python
OUT=../models
PID=$(cat "$RUN/pid" 2>/dev/null || true)
resume() { [ -n "$PID" ] && kill -CONT "$PID" 2>/dev/null || true; }
trap resume EXIT
[ -n "$PID" ] && kill -STOP "$PID" 2>/dev/null || true
$PY -m cmr.evaluate --checkpoint "$RUN/$CKPT" --data "$TEST" --frames "$FRAMES" --hypotheses "$HYPOTHESES" \
    --out "$RUN/final_eval.json" > /dev/null
$PY -m cmr.export --checkpoint "$RUN/$CKPT" --out "$OUT" --validation "$RUN/final_eval.json" > /dev/null
$PY -m cmr.diagnose --checkpoint "$RUN/$CKPT" --data "$TEST" --frames "$FRAMES" > "$RUN/diagnose.json"
$PY -m cmr.bench --models "$OUT" --repeats 30 > "$RUN/bench.json"
$PY -m cmr.plots "$RUN" --out "$OUT/training_curves.png"
NOTES=()
[ -f "$RUN/notes.md" ] && NOTES=(--notes "$RUN/notes.md")
$PY -m cmr.model_card --models "$OUT" --eval "$RUN/final_eval.json" --bench "$RUN/bench.json" \
    --train-data "$TRAIN" --test-data "$TEST" --curves training_curves.png --diagnose "$RUN/diagnose.json" "${NOTES[@]}"
du -sh "$OUT"
