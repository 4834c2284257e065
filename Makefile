# `make test` builds everything from nothing: a virtual environment, the package with its
# test and nuScenes extras, then the suite.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.evgrid-installed

.PHONY: install test bench demo clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU build of torch; any other spec pulls gigabytes of CUDA packages.
	$(PY) -m pip install -q "torch==2.13.0"
	$(PY) -m pip install -q -e ".[dev,nuscenes,bench,ros,rerun,fast,ray,live,live-test]"
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports
	$(PY) -m pytest -q -n 2

bench: $(STAMP)
	$(PY) benchmarks/bench_core.py
	$(PY) benchmarks/bench_ism.py
	$(VENV)/bin/evgrid bench

# The README's first command: set up, then map simulated scenes with the shipped Ev-Net.
demo: $(STAMP)
	$(VENV)/bin/evgrid demo --out out/demo --overwrite

clean:
	rm -rf $(VENV) build dist .pytest_cache
