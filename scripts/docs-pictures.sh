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
maps=$(mktemp -d)
cp maps/demo.bin maps/demo.json "$maps"/
port=$((20000 + RANDOM % 10000))
./target/release/cmr-agent serve --host 127.0.0.1 --port "$port" --maps "$maps" 2>"$maps/server.log" &
server=$!
trap 'kill $server 2>/dev/null; wait $server 2>/dev/null; rm -rf "$maps"' EXIT
for _ in $(seq 1 300); do
  curl -fs "http://127.0.0.1:$port/ready" >/dev/null 2>&1 && break
  sleep 0.2
done
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
