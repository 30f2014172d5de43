# The two commands a newcomer needs: `make serve` and `make test`.
PORT ?= 8080
CARGO ?= cargo
PYTHON := .venv/bin/python

.PHONY: serve test build runtime python rust-test python-test bench-server openapi

serve: build runtime
	./target/release/cmr-agent serve --port $(PORT)

test: build runtime python
	$(CARGO) test --release
	cd training && ../$(PYTHON) -m pytest -q tests

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
