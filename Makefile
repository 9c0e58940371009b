# afmid developer and user entry points. Everything runs inside .venv, created on demand.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
AFMID := $(VENV)/bin/afmid
STAMP := $(VENV)/.installed
DEMO_DIR ?= demo_output
RESULTS ?= results
BENCH_ARGS ?=
CONFIGS := $(wildcard configs/*.yaml)
RUNS := $(patsubst configs/%.yaml,$(RESULTS)/%.run.h5,$(CONFIGS))

.PHONY: help venv demo test batch bench clean
.DEFAULT_GOAL := help

help:
	@echo "make demo   - set up .venv, simulate a soft-polymer trace, fit it, write a report"
	@echo "make test   - set up .venv with test extras and run the test suite"
	@echo "make batch  - simulate and fit every config in configs/ into $(RESULTS)/ (use -j N)"
	@echo "make bench  - benchmarks in one table (afmid vs SciPy / PySINDy, scaling, start-up, batch);"
	@echo "              BENCH_ARGS=--quick for a smoke run"
	@echo "many traces with one config: afmid batch CONFIG --inputs 'traces/*.csv' -j N -o DIR"

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m afmid.demo --output $(DEMO_DIR)

test: $(STAMP)
	$(PY) -m pytest -q

# One simulate + fit per config; make only re-runs what changed (parallel with make -j N).
# Each config carries its own cantilever and model, so this stays a pattern rule rather than
# `afmid batch`, which fits many traces with one config (see `afmid batch --help`).
$(RESULTS)/%.trace.h5: configs/%.yaml $(STAMP)
	@mkdir -p $(RESULTS)
	$(AFMID) -q simulate $< -o $@ --overwrite

$(RESULTS)/%.run.h5: configs/%.yaml $(RESULTS)/%.trace.h5
	$(AFMID) -q fit $< --set data.path=$(abspath $(RESULTS)/$*.trace.h5) -o $@ --overwrite

batch: $(RUNS)
	@echo "batch results in $(RESULTS)/"

bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) bench/run_all.py $(BENCH_ARGS)

clean:
	rm -rf $(DEMO_DIR) $(RESULTS) .pytest_cache
