# The two commands of the README. Both install first (scripts/setup.sh is a no-op when up to date).
BIN := .venv/bin
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: setup repro test smoke

setup:
	@bash scripts/setup.sh

## Run the whole pipeline on the profile in params.yaml (the default profile as committed).
repro: setup
	dvc repro

## Run the test suite (includes the smoke end-to-end run).
test: setup
	python -m pytest -q

## Switch params.yaml to the smoke profile and run every stage end to end (about a minute or two).
smoke: setup
	rpod params smoke && dvc repro
