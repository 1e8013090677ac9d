# Two-command setup: `make train` and `make test` create .venv and install everything first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
ARGS ?=

.PHONY: setup train test bench clean-venv

setup: $(STAMP)

# pip's download bars go to a terminal only; a CI log gets one line per package instead
INSTALL = $(BIN)/python -m pip install --progress-bar $$([ -t 1 ] && echo on || echo off)

# torch first: its CPU wheel (2.13.0) must be in place before anything asks for an unpinned torch,
# which would pull several GB of CUDA packages.
$(STAMP): pyproject.toml
	@echo "== setup 1/4 (first run only, a few minutes): virtual environment $(VENV)"
	$(PYTHON) -m venv $(VENV)
	@echo "== setup 2/4: pip"
	$(INSTALL) --quiet --upgrade pip
	@echo "== setup 3/4: torch 2.13.0, CPU build (about 200 MB, the longest step)"
	$(INSTALL) torch==2.13.0
	@echo "== setup 4/4: mrta_rl and its dependencies, .[dev] (torchrl, gymnasium, pettingzoo, hydra, pytest, stable-baselines3, ...)"
	$(INSTALL) -e ".[dev]"
	touch $(STAMP)
	@echo "== setup done: $(VENV) is ready"

train: $(STAMP)  ## train the reference learner (subG-CQL) on System-II: make train ARGS="learner=cql system=system1"
	$(BIN)/python scripts/train.py $(ARGS)

test: $(STAMP)  ## the test suite on every core, in random order (fast tests; slow and gpu markers excluded)
	$(BIN)/python -m pytest -n auto $(ARGS)

bench: $(STAMP)  ## env throughput table, written to bench_env.json
	$(BIN)/python scripts/bench_env.py $(ARGS)

clean-venv:
	rm -rf $(VENV)
