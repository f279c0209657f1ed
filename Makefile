# The commands a person runs. `make run` and `make test` work on a fresh clone.
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
HOST   ?= 127.0.0.1
PORT   ?= 8000
export FLEETHEALTH_REQUIRE_PG ?= 1

.PHONY: run demo test test-fast lint typecheck bench validate openapi migrate clean

# The service (with its dev tools) and the client package it ships beside (clients/python), both
# editable; the client is a separate distribution, used by simulate/replay, bench/ and the tests.
$(STAMP): pyproject.toml constraints.txt clients/python/pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) on PATH (or make PYTHON=/path/to/python3.11)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e "./clients/python[arrow]" -e ".[dev]"
	@touch $(STAMP)

## Create the environment, migrate the embedded SQLite database and serve on 127.0.0.1:8000.
run: $(STAMP)
	$(BIN)/fleethealth serve --host $(HOST) --port $(PORT)

## The same, plus the built-in simulator feeding a demo fleet (prints the URL and a demo key).
demo: $(STAMP)
	$(BIN)/fleethealth serve --host $(HOST) --port $(PORT) --demo

## The whole test suite: estimators, API on SQLite and PostgreSQL, end-to-end.
test: $(STAMP)
	$(BIN)/python -m pytest -q

## Estimator and API tests only (no end-to-end processes).
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not e2e"

lint: $(STAMP)
	$(BIN)/ruff check app estimators fleethealth_tools clients tests bench scripts

typecheck: $(STAMP)
	$(BIN)/mypy

migrate: $(STAMP)
	$(BIN)/fleethealth migrate

openapi: $(STAMP)
	$(BIN)/fleethealth export-openapi --output openapi/openapi.json

## Benchmarks print figures (never asserted).
bench: $(STAMP)
	$(BIN)/python bench/bench_fakf.py
	$(BIN)/python bench/bench_deterioration_ekf.py
	$(BIN)/python bench/bench_stmmae.py
	$(BIN)/python bench/bench_darr_fekf.py
	$(BIN)/python bench/bench_ingest.py
	$(BIN)/python bench/bench_ws.py
	$(BIN)/python bench/bench_events.py

## Regenerate docs/validation.md from the simulators and the FLEA runs.
validate: $(STAMP)
	$(BIN)/python scripts/validate_fakf.py
	$(BIN)/python scripts/validate_deterioration_ekf.py
	$(BIN)/python scripts/validate_stmmae.py
	$(BIN)/python scripts/validate_darr_fekf.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache data
