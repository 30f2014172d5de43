# The two commands a newcomer needs: `make serve` and `make test`.
PORT ?= 8080
CARGO ?= cargo
PYTHON := .venv/bin/python

.PHONY: serve test test-ui chromium docs-pictures build runtime python bench openapi check-schema

serve: build runtime
	./target/release/cmr-agent serve --port $(PORT)

# `cargo test --release` also builds target/release/cmr-agent (the tests run it); a separate
# `cargo build` would compile the dependencies a second time with other features.
# The browser test (tests/web_ui.rs) is part of `cargo test`; it needs Chromium + chromedriver.
test: runtime python chromium
	$(CARGO) test --release
	cd training && ../$(PYTHON) -m pytest -q tests
	bash scripts/check-schema.sh

# The API contract: schemathesis, every check, against a live server (part of `make test`).
check-schema: build runtime
	bash scripts/check-schema.sh

# The web page in headless Chromium alone (fails, instead of skipping, without a browser).
test-ui: runtime chromium
	CMR_REQUIRE_BROWSER=1 $(CARGO) test --release --test web_ui

# Debian's chromium and chromium-driver (apt-get; does nothing when both are installed).
chromium:
	bash scripts/install-chromium.sh

# Remakes docs/overlay-demo.png and docs/web-ui.png.
docs-pictures: runtime python chromium
	bash scripts/docs-pictures.sh

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
