#!/usr/bin/env bash
# Contract check: schemathesis (PyPI, pinned, in .tools/st) runs every check and every phase
# (examples, coverage, fuzzing, stateful) against a live server (tiny test model, a copy of the
# demo map, an admin token) on a free loopback port. Exit status 0 only when it finds nothing.
# Configuration, and what JSON Schema cannot state per operation: tests/schemathesis/schemathesis.toml.
#   bash scripts/check-schema.sh [max-examples]
set -euo pipefail
cd "$(dirname "$0")/.."
version=4.32.5
if ! .tools/st/bin/schemathesis --version 2>/dev/null | grep -q "$version"; then
  python3 -m venv .tools/st
  .tools/st/bin/pip install --quiet "schemathesis==$version"
fi
source scripts/demo-server.sh
start_demo_server --models tests/fixtures/tiny-model --admin-token schema-check
# One worker: with two, CPython 3.11.7's ast module fails under hypothesis' lambda descriptions
# in the coverage phase ("SystemError: AST constructor recursion depth mismatch", an
# interpreter bug of concurrent ast.parse calls, not the API's).
.tools/st/bin/schemathesis --config-file tests/schemathesis/schemathesis.toml run openapi/openapi.json \
  --url "http://127.0.0.1:$port" --checks all \
  -H "Authorization: Bearer schema-check" --max-examples "${1:-50}" --seed 1 --workers 1
