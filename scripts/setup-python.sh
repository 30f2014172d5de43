#!/usr/bin/env bash
# Creates .venv with the training pipeline's pinned packages (PyPI only).
# Idempotent: a venv whose requirements stamp matches is left as it is.
set -euo pipefail
cd "$(dirname "$0")/.."
req=training/requirements.txt
stamp=.venv/.requirements.sha256
want=$(sha256sum "$req" | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
python3 -m venv .venv
.venv/bin/pip install --quiet --upgrade pip
.venv/bin/pip install --quiet -r "$req"
echo "$want" > "$stamp"
