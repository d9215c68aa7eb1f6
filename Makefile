# thermocal: two commands on a fresh machine with Python 3.11 (or 3.12, 3.13) and make:
#   make demo        creates .venv, installs thermocal, calibrates the sample runs into ./registry
#   make test        runs the whole test suite
#   make test-fast   the suite without the tests marked slow (Prefect server, browser, wheel, long simulations)
#   make lint        ruff check, ruff format --check and mypy (CONTRIBUTING.md: run it before landing)
#   make docs        the documentation site into ./site (mkdocs build --strict)
# Another interpreter: make test-fast PYTHON=python3.12 VENV=.venv-3.12 EXTRAS=test
PYTHON ?= python3.11
VENV ?= .venv
EXTRAS ?= test,lint,docs
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Prefect: no telemetry (no network here). Its state lives where it does outside make: PREFECT_HOME if set, else
# the per-user data folder (`thermocal server status` prints it; README, "Where Prefect records the runs").
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export DO_NOT_TRACK := 1

.PHONY: demo test test-fast lint docs venv clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or make PYTHON=python3)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[$(EXTRAS)]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/thermocal inspect sample_data/standard_short.mcap
	$(BIN)/thermocal inspect sample_data/standard_short_parquet
	$(BIN)/thermocal calibrate sample_data/standard_short.mcap --registry registry
	$(BIN)/thermocal calibrate sample_data/standard_short_parquet --registry registry --thermal-model poly2
	$(BIN)/thermocal passport log AU-0001 --registry registry
	$(BIN)/thermocal passport verify --registry registry

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

clean:
	rm -rf $(VENV) registry demo_out site
