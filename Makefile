# The two commands a newcomer needs: `make serve` and `make test`.
PORT ?= 8080
CARGO ?= cargo
PYTHON := .venv/bin/python

.PHONY: serve test build runtime python bench openapi check-schema

serve: build runtime
	./target/release/cmr-agent serve --port $(PORT)

# `cargo test --release` also builds target/release/cmr-agent (the tests run it); a separate
# `cargo build` would compile the dependencies a second time with other features.
test: runtime python
	$(CARGO) test --release
	cd training && ../$(PYTHON) -m pytest -q tests
	bash scripts/check-schema.sh

# The API contract: schemathesis, every check, against a live server (part of `make test`).
check-schema: build runtime
	bash scripts/check-schema.sh

build:
	$(CARGO) build --release

runtime:
	bash scripts/install-onnxruntime.sh

python:
	bash scripts/setup-python.sh

# Load benchmark of the server on loopback (starts its own servers on free ports; oha from
# crates.io into .tools/bin): sequential p50/p99, c16 req/s, CPU and FLOPs per request, overload.
bench: build runtime
	bash scripts/install-oha.sh
	python3 scripts/bench.py --storm --out bench.json

# Regenerates the committed OpenAPI document (a test fails when it is stale).
openapi: build
	./target/release/cmr-agent print-schema > openapi/openapi.json
