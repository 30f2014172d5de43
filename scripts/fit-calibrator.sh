#!/usr/bin/env bash
# Fit the calibrator (issue 30) of a model set: `cmr-agent eval` on frames the set never trained on,
# in the paper's protocol and from fleet-grade priors, with keep-prior off and on, and the fleet
# priors again stated as a bound (--prior-bound 30,5: the request's prior_bound, whose answers the
# `bounded` signal tells apart), then `python -m cmr.calibrate` writes `calibrator` into
# MODELS/manifest.json, with one threshold for unbounded requests and one for bounded ones.
#
#   scripts/fit-calibrator.sh MODELS REAL
#
# REAL: a folder of KITTI-layout real sequences the model never trained on (for a model trained on
# `cmr.real_split`'s train half: its val half; never ../shared/real-dev, which checks the fit); the
# folds follow the drives of the rigs.json beside it (`cmr.real_split` writes one).
# Synthetic frames of fresh seeds are made under $CAL (default ~/.cache/cmr-agent/data/cal) when
# missing: 80 of the generator's default worlds (seed 7300) and 40 of the classic world (7400).
# Environment: CAL, REAL_CASES (cases per real frame, default 8), OUT (eval outputs, default
# $CAL/evals/<manifest sha>; an eval whose cases.json is already there is reused), CMR_AGENT_BIN,
# NICE (default 5).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
[ $# -eq 2 ] || { sed -n 2,17p "$0"; exit 2; }
MODELS=$(readlink -f "$1"); REAL=$(readlink -f "$2")
CAL=${CAL:-$HOME/.cache/cmr-agent/data/cal}
BIN=${CMR_AGENT_BIN:-$ROOT/target/release/cmr-agent}
NICE=${NICE:-5}
REAL_CASES=${REAL_CASES:-8}
OUT=${OUT:-$CAL/evals/$(sha256sum "$MODELS/manifest.json" | cut -c1-12)}

[ -f "$CAL/synth/.done" ] || { "$BIN" synth --out "$CAL/synth" --sequences 4 --frames 20 --seed 7300 --style test --quiet &&
  touch "$CAL/synth/.done"; }
[ -f "$CAL/classic/.done" ] || { "$BIN" synth --out "$CAL/classic" --sequences 2 --frames 20 --seed 7400 --style test \
  --world classic --look classic --quiet && touch "$CAL/classic/.done"; }

# one eval: data folder, its short name, cases per frame, seed, regime; each search setting
cases=()
run() {
  local data=$1 name=$2 per=$3 seed=$4 priors=$5 setting
  mkdir -p "$OUT/cases"
  local settings=("keep-false --keep-prior false" "keep-true --keep-prior true")
  [ "$priors" = fleet ] && settings+=("bounded --keep-prior true --prior-bound 30,5")
  for setting in "${settings[@]}"; do
    local out=$OUT/$name-$priors-${setting%% *}
    # an eval already in OUT is reused (OUT is per model set unless given)
    [ -f "$out/cases.json" ] && { cases+=("$out/cases.json"); continue; }
    # shellcheck disable=SC2086
    nice -n "$NICE" "$BIN" eval --data "$data" --models "$MODELS" --perturbations "$OUT/cases/$name-$priors.json" \
      --cases-per-frame "$per" --seed "$seed" --priors "$priors" ${setting#* } \
      --out "$out" --no-baseline --worst 0 --quiet
    cases+=("$out/cases.json")
  done
}

drives=()
[ -f "$REAL/../rigs.json" ] && drives=(--drives "$(readlink -f "$REAL/../rigs.json")")
run "$REAL" real $REAL_CASES 3003 protocol; run "$REAL" real $REAL_CASES 3004 fleet
run "$CAL/synth" synth 2 3005 protocol; run "$CAL/synth" synth 2 3006 fleet
run "$CAL/classic" classic 2 3007 protocol; run "$CAL/classic" classic 2 3008 fleet

cd "$ROOT/training"
"$ROOT/.venv/bin/python" -m cmr.calibrate --models "$MODELS" "${drives[@]}" --cases "$(IFS=,; echo "${cases[*]}")"
