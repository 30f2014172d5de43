#!/usr/bin/env bash
# Installs ONNX Runtime's shared library into runtime/ from the PyPI `onnxruntime` wheel
# (the only place the project may fetch it from). The server loads it with `ort`'s load-dynamic.
set -euo pipefail
cd "$(dirname "$0")/.."
version=1.31.1
dest=runtime
lib="$dest/libonnxruntime.so.$version"
if [ -f "$lib" ]; then
  exit 0
fi
mkdir -p "$dest"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download --quiet --no-deps --only-binary=:all: \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --python-version 3.11 --implementation cp -d "$tmp" "onnxruntime==$version"
wheel=$(ls "$tmp"/onnxruntime-*.whl)
python3 - "$wheel" "$tmp/$(basename "$lib")" <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z:
    name = next(n for n in z.namelist() if n.endswith("capi/" + sys.argv[2].rsplit("/", 1)[1]))
    with z.open(name) as src, open(sys.argv[2], "wb") as dst:
        dst.write(src.read())
PY
mv "$tmp/$(basename "$lib")" "$lib"
ln -sf "$(basename "$lib")" "$dest/libonnxruntime.so"
echo "installed $lib"
