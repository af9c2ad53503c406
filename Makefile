# Everyday commands. `make serve` and `make test` set up what is missing first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
HOST ?= 127.0.0.1
PORT ?= 8000
# the embedded deployment's data dir for `make serve` (empty: ./data); DATA=data/demo/service serves the demo's map
DATA ?=

.PHONY: web setup serve worker test test-unit test-integration lint bench-ingest clean-data lock

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	# the splicing stage's numba kernels, compiled once into numba's cache (30-40 s; loaded in ~1 s after)
	$(BIN)/python -m csr_core.single_trip.compiled
	touch $@

# The embedded default: SQLite under ./data (or DATA), jobs in-process; admin key from CSR_ADMIN_KEY or
# DATA/admin.key. After `make demo ARGS=--exit`: `make serve DATA=data/demo/service` serves its map again.
serve: setup
	$(BIN)/csr serve --host $(HOST) --port $(PORT) $(if $(DATA),--data-dir $(DATA))

# The README's first command: the service (embedded) on a simulated Karlsruhe fleet, uploaded over HTTP,
# processed and scored against the ground truth; serves until Ctrl-C. Data in ./data/demo.
# More options: make demo ARGS='--exit --trips 6' (see .venv/bin/csr demo --help)
.PHONY: demo
demo: setup
	$(BIN)/csr demo --host $(HOST) --port $(PORT) $(ARGS)

# The distributed deployment's worker (needs CSR_DATABASE_URL and CSR_REDIS_URL)
worker: setup
	$(BIN)/csr worker

test: setup services/web/node_modules/.package-lock.json
	bash scripts/system-deps
	$(BIN)/python -m services.devsetup
	$(BIN)/python -m pytest

test-unit: setup
	bash scripts/system-deps  # promtool and docker-compose for tests/unit/test_deploy.py
	$(BIN)/python -m pytest -m unit

test-integration: setup
	bash scripts/system-deps
	$(BIN)/python -m services.devsetup
	$(BIN)/python -m pytest -m integration

lint: setup
	$(BIN)/ruff check services workers migrations tests csr_core
	$(BIN)/ruff format --check csr_core services workers migrations tests
	$(BIN)/mypy

# Ingest throughput (BENCHMARKS.md); the distributed row uses a scratch database on the local PostGIS
bench-ingest: setup
	$(BIN)/python -m services.devsetup
	psql -h 127.0.0.1 -U postgres -qc 'DROP DATABASE IF EXISTS csr_bench' -c 'CREATE DATABASE csr_bench'
	psql -h 127.0.0.1 -U postgres -d csr_bench -qc 'CREATE EXTENSION postgis'
	CSR_BENCH_DATABASE_URL=postgresql+psycopg://postgres@127.0.0.1:5432/csr_bench $(BIN)/csr bench-ingest --write BENCHMARKS.md

clean-data:
	rm -rf data

# The viewer and ops bundle in services/web/dist (committed); needs Node.js and npm
web: services/web/node_modules/.package-lock.json
	cd services/web && npm run build

# playwright-core for the browser tests (and esbuild, MapLibre for `make web`)
services/web/node_modules/.package-lock.json: services/web/package-lock.json
	cd services/web && npm ci --no-audit --no-fund

# requirements.lock: the image's pinned, hashed dependencies (Dockerfile), from pyproject.toml
lock: setup
	$(BIN)/python -m pip install --quiet uv
	$(BIN)/uv pip compile pyproject.toml --extra ops --generate-hashes --python-version 3.11 \
	  --python-platform x86_64-manylinux_2_36 --no-header --annotation-style line -o requirements.lock.new
	{ sed -n '1,4p' requirements.lock; cat requirements.lock.new; } > requirements.lock && rm requirements.lock.new
