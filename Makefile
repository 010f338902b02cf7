# The two commands of the README. Both install first (scripts/setup.sh is a no-op when up to date).
BIN := .venv/bin
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: setup repro paper test smoke

setup:
	@bash scripts/setup.sh

## Run the whole pipeline on the profile in params.yaml (the default profile as committed).
repro: setup
	rpod params --check
	dvc repro

## The paper profile end to end, for a GPU box (README, "GPU and the paper profile"): params.yaml switched to the
## paper profile, the default pipeline, then the optional ablation. `rpod params default` switches back.
paper: setup
	rpod params paper
	dvc repro
	dvc repro optional/dvc.yaml:ablation

## Run the test suite (includes the smoke end-to-end run), a whole test file at a time on each of up to 4 workers
## (pytest-xdist; two on a 2-core machine); tests/conftest.py starts the longest files first.
test: setup
	ruff check . && ruff format --check .
	python -m pytest -q -n logical --maxprocesses 4 --dist loadfile --no-loadscope-reorder

## Run every stage end to end on the smoke profile in a temporary copy of the repository (a few minutes);
## the checkout's params.yaml, reports and dvc.lock stay as they were. Prints where the results are.
smoke: setup
	python scripts/smoke.py
