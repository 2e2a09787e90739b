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

.PHONY: setup repro test test-fast lint params bench clean push pull exp

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

setup: $(STAMP)

repro: setup  ## check every stage's params (seconds), then run the whole DVC pipeline on the configured dataset
	$(BIN)/python -m pipelines.preflight
	$(BIN)/dvc repro

test: setup  ## lint, then the whole test suite
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

test-fast: setup  ## lint, then the tests not marked slow (no Ray, training or stage runs; under a minute)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -m "not slow"

lint: setup
	$(BIN)/ruff check .

params: setup  ## re-compose params.yaml from conf/ (e.g. make params ARGS="scale=smoke"), then check every stage's params
	$(BIN)/python -m pipelines.config $(ARGS)
	$(BIN)/python -m pipelines.preflight

push: setup  ## upload the outputs that dvc.lock records to the DVC remote (README, "Versions")
	$(BIN)/dvc push $(ARGS)

pull: setup  ## download the outputs that dvc.lock records from the DVC remote into artifacts/
	$(BIN)/dvc pull $(ARGS)

# The summary metrics (artifacts/eval/summary.json) always; params only where experiments differ;
# no code or data hashes. KEEP adds columns by regex, e.g. make exp KEEP='train_vae\.lr'.
EXP_KEEP := .*\.FID$$|.*\.R_precision_top3$$$(if $(KEEP),|$(KEEP))
EXP_DROP := Created$$|Executor$$|(artifacts|data|models|pipelines|stages)/

exp: setup  ## DVC experiments in a table that fits a terminal (README, "DVC views")
	$(BIN)/dvc exp show --no-pager --only-changed --keep '$(EXP_KEEP)' --drop '$(EXP_DROP)' $(ARGS)

bench: setup
	$(BIN)/python benchmarks/extract_features.py

clean:
	rm -rf artifacts .ray_storage wandb
