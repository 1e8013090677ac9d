# Two-command setup: `make train` and `make test` create .venv and install everything first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
ARGS ?=

.PHONY: setup train test bench clean-venv

setup: $(STAMP)

# torch first: its CPU wheel (2.13.0) must be in place before anything asks for an unpinned torch,
# which would pull several GB of CUDA packages.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

train: $(STAMP)  ## train the reference learner (subG-CQL) on System-II: make train ARGS="learner=cql system=system1"
	$(BIN)/python scripts/train.py $(ARGS)

test: $(STAMP)  ## the test suite (fast tests; slow and gpu markers excluded)
	$(BIN)/python -m pytest $(ARGS)

bench: $(STAMP)  ## env throughput table, written to bench_env.json
	$(BIN)/python scripts/bench_env.py $(ARGS)

clean-venv:
	rm -rf $(VENV)
