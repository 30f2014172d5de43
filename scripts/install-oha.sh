#!/usr/bin/env bash
# Installs the oha HTTP load generator (crates.io) into .tools/bin for the benchmarks.
# Idempotent: an installed oha of the pinned version is left as it is.
set -euo pipefail
cd "$(dirname "$0")/.."
version=1.16.0
if [ -x .tools/bin/oha ] && .tools/bin/oha --version 2>/dev/null | grep -q "$version"; then
  exit 0
fi
cargo install oha --version "$version" --locked --root .tools --no-default-features --features rustls
