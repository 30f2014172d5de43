# The two commands a newcomer needs: `make serve` and `make test`.
PORT ?= 8080
CARGO ?= cargo
PYTHON := .venv/bin/python

.PHONY: serve test build runtime python bench-server openapi check-schema

serve: build runtime
	./target/release/cmr-agent serve --port $(PORT)

test: build runtime python
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

# Load benchmark of the server on loopback (starts its own server on a free port).
bench-server: build runtime
	python3 scripts/bench-server.py --spawn

# Regenerates the committed OpenAPI document (a test fails when it is stale).
openapi: build
	./target/release/cmr-agent print-schema > openapi/openapi.json
