# The commands a person runs. `make run` and `make test` work on a fresh clone.
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
HOST   ?= 127.0.0.1
PORT   ?= 8000
NPM    ?= npm
# The dashboard's chart library (uPlot, pinned by package-lock.json), copied from node_modules
# into the app package so that the app serves it itself (no CDN) and the wheel carries it.
VENDOR := app/dashboard/static/vendor
UPLOT  := $(VENDOR)/uPlot.iife.min.js
export FLEETHEALTH_REQUIRE_PG ?= 1
# Test processes (pytest-xdist); TEST_PROCESSES=0 runs the suite in one process.
TEST_PROCESSES ?= 2

.PHONY: run demo test test-fast lint typecheck bench validate openapi migrate screenshots clean

# The service (with its dev tools) and the client package it ships beside (clients/python), both
# editable; the client is a separate distribution, used by simulate/replay, bench/ and the tests.
$(STAMP): pyproject.toml constraints.txt clients/python/pyproject.toml | $(UPLOT)
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) on PATH (or make PYTHON=/path/to/python3.11)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e "./clients/python[arrow]" -e ".[dev]"
	@touch $(STAMP)

$(UPLOT): package.json package-lock.json
	@command -v $(NPM) >/dev/null || { echo "need npm (Node.js) to install the dashboard's chart library"; exit 1; }
	$(NPM) ci --no-audit --no-fund --ignore-scripts --loglevel=error
	mkdir -p $(VENDOR)
	cp node_modules/uplot/dist/uPlot.iife.min.js node_modules/uplot/dist/uPlot.min.css $(VENDOR)/
	cp node_modules/uplot/LICENSE $(VENDOR)/uPlot.LICENSE

## Create the environment, migrate the embedded SQLite database and serve on 127.0.0.1:8000.
run: $(STAMP) $(UPLOT)
	$(BIN)/fleethealth serve --host $(HOST) --port $(PORT)

## The same, plus the built-in simulator feeding a demo fleet (prints the URL and a demo key).
demo: $(STAMP) $(UPLOT)
	$(BIN)/fleethealth serve --host $(HOST) --port $(PORT) --demo

## The whole test suite: estimators, API on SQLite and PostgreSQL, end-to-end.
test: $(STAMP) $(UPLOT)
	$(BIN)/python -m pytest -q -n $(TEST_PROCESSES) --dist loadgroup

## Estimator and API tests only (no end-to-end processes).
test-fast: $(STAMP) $(UPLOT)
	$(BIN)/python -m pytest -q -n $(TEST_PROCESSES) --dist loadgroup -m "not e2e"

lint: $(STAMP)
	$(BIN)/ruff check app estimators fleethealth_tools clients tests bench scripts

typecheck: $(STAMP)
	$(BIN)/mypy

migrate: $(STAMP)
	$(BIN)/fleethealth migrate

openapi: $(STAMP)
	$(BIN)/fleethealth export-openapi --output openapi/openapi.json

## Benchmarks print figures (never asserted).
bench: $(STAMP) $(UPLOT)
	$(BIN)/python bench/bench_fakf.py
	$(BIN)/python bench/bench_deterioration_ekf.py
	$(BIN)/python bench/bench_stmmae.py
	$(BIN)/python bench/bench_darr_fekf.py
	$(BIN)/python bench/bench_ingest.py
	$(BIN)/python bench/bench_ws.py
	$(BIN)/python bench/bench_series.py
	$(BIN)/python bench/bench_events.py

## Regenerate docs/validation.md from the simulators and the FLEA runs.
validate: $(STAMP)
	$(BIN)/python scripts/validate_fakf.py
	$(BIN)/python scripts/validate_deterioration_ekf.py
	$(BIN)/python scripts/validate_stmmae.py
	$(BIN)/python scripts/validate_darr_fekf.py

## Regenerate the dashboard screenshots in docs/img/ (a server, the simulator and Chromium).
screenshots: $(STAMP) $(UPLOT)
	$(BIN)/python scripts/screenshots.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache data node_modules $(VENDOR)
