#!/usr/bin/env bash
# Remakes the pictures the README shows: docs/overlay-demo.png (POST /v1/maps/demo/overlay with
# the demo request, from a server on a free loopback port) and docs/web-ui.png (the browser
# test's screenshot). Both are reduced to a 256-colour palette (Pillow, from the project's venv)
# to keep the repository small. Needs runtime/ and .venv/ (make runtime python) and Chromium
# (scripts/install-chromium.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
# The browser test first: it also builds target/release/cmr-agent.
CMR_UPDATE_DOCS=1 CMR_REQUIRE_BROWSER=1 cargo test --release --test web_ui -q
source scripts/demo-server.sh
start_demo_server
curl -fsS -X POST -H 'content-type: application/json' --data-binary @examples/localize-demo.json \
  "http://127.0.0.1:$port/v1/maps/demo/overlay" -o docs/overlay-demo.png
.venv/bin/python - docs/overlay-demo.png docs/web-ui.png <<'PY'
import os, sys
from PIL import Image
for path in sys.argv[1:]:
    image = Image.open(path).convert("RGB")
    image.quantize(colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(path, optimize=True)
    print(f"{path}: {image.width}x{image.height}, {os.path.getsize(path) // 1024} KiB")
PY
