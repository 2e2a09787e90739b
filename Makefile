# The two commands a user runs (README): `make repro` and `make test`. Both create .venv when
# missing, install the pinned dependencies when pyproject.toml changed, and are quick after that.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

export PATH := $(abspath $(BIN)):$(PATH)
export HF_HUB_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1
export WANDB_MODE ?= offline
export DVC_NO_ANALYTICS ?= 1
export RAY_USAGE_STATS_ENABLED ?= 0

.PHONY: setup repro test test-fast lint params bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

setup: $(STAMP)

repro: setup  ## run the whole DVC pipeline on the configured dataset (default: embedded)
	$(BIN)/dvc repro

test: setup  ## lint, then the whole test suite
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

test-fast: setup  ## lint, then the tests not marked slow (no Ray, training or stage runs; under a minute)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -m "not slow"

lint: setup
	$(BIN)/ruff check .

params: setup  ## re-compose params.yaml from conf/ (e.g. make params ARGS="scale=smoke")
	$(BIN)/python -m pipelines.config $(ARGS)

bench: setup
	$(BIN)/python benchmarks/extract_features.py

clean:
	rm -rf artifacts .ray_storage wandb
