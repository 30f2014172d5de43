#!/usr/bin/env bash
# Regenerate docs/eval's measured outputs with the shipped models/ and the server's default search:
# the synthetic test set (eval.json, cases.json, tables.md, Fig. 5), world-v2 validation
# (v2-val-tables.md), real-dev under the paper's protocol, from fleet priors and with the bound
# stated (real-dev-tables.md and calibration/: tables and reliability diagrams), and the manifest's
# copy. Run after any change to models/ or to the search's defaults; take it on an idle machine
# (eval records timings too). About 3 minutes on 2 cores.
#
# Needs: target/release/cmr-agent, ../shared/real-dev, and the synthetic sets that
# `scripts/train-v7.sh data` makes under $DATA (default ~/.cache/cmr-agent/data). WORK (default
# /tmp/ev) keeps the raw outputs, whose paths the tables' command lines name.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
DATA=${DATA:-$HOME/.cache/cmr-agent/data}
WORK=${WORK:-/tmp/ev}
B=./target/release/cmr-agent
for need in "$B" ../shared/real-dev "$DATA/synth-test/.done" "$DATA/v2-val-flat"; do
  [ -e "$need" ] || { echo "missing $need" >&2; exit 2; }
done
rm -rf "$WORK" && mkdir -p "$WORK"
e() { "$B" eval --models models --quiet --worst 0 "$@"; }
e --data ../shared/real-dev --perturbations docs/eval/real-dev-perturbations.json --no-baseline --out "$WORK/dev"
e --data ../shared/real-dev --perturbations docs/eval/real-dev-fleet-perturbations.json --no-baseline --out "$WORK/devf"
e --data ../shared/real-dev --perturbations docs/eval/real-dev-fleet-perturbations.json --prior-bound 30,5 --no-baseline \
  --out "$WORK/bdevf"
e --data "$DATA/v2-val-flat" --perturbations docs/eval/v2-val-perturbations.json --out "$WORK/v2-val"
e --data "$DATA/synth-test" --perturbations docs/eval/perturbations.json --out "$WORK/synth-test"

cp "$WORK/dev/tables.md" docs/eval/real-dev-tables.md
for pair in dev:paper devf:fleet bdevf:fleet-bounded; do
  cp "$WORK/${pair%%:*}/tables.md" "docs/eval/calibration/real-dev-${pair#*:}-tables.md"
  cp "$WORK/${pair%%:*}/reliability.png" "docs/eval/calibration/real-dev-${pair#*:}-reliability.png"
done
cp "$WORK/v2-val/tables.md" docs/eval/v2-val-tables.md
for f in eval.json cases.json tables.md fig5_rotation.png fig5_translation.png; do
  cp "$WORK/synth-test/$f" "docs/eval/$f"
done
cp models/manifest.json docs/eval/model-manifest.json
for d in dev devf bdevf v2-val synth-test; do
  echo "$d: $(grep -m1 '^| cmr-agent |' "$WORK/$d/tables.md")"
done
