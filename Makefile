# Everyday commands. Each target installs what it needs into .venv first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
GAME ?= pong
ARGS ?=

.PHONY: install install-test train test test-slow lint format typecheck clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .

install-test: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test]"

# The main job: the Nature DQN on an Atari game (GAME=breakout, ARGS="--seed 1" ...).
train: install
	$(BIN)/dqnlab train --env $(GAME) --preset nature $(ARGS)

# The test suite CI runs: lint, format and type checks, then every test not marked slow.
test: install-test
	$(BIN)/ruff check src tests
	$(BIN)/ruff format --check src tests
	$(BIN)/mypy src
	$(BIN)/python -m pytest -q

# Slow tests (minutes): the classic preset solves CartPole-v1 for 3 seeds; the sweep on
# Ray clusters on 127.0.0.1 (lost node, killed driver, Ctrl-C, auto and ray://).
test-slow: install-test
	$(BIN)/python -m pytest -q -m slow

lint: install-test
	$(BIN)/ruff check src tests
	$(BIN)/ruff format --check src tests

format: install-test
	$(BIN)/ruff format src tests
	$(BIN)/ruff check --fix src tests

typecheck: install-test
	$(BIN)/mypy src

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache .ruff_cache .mypy_cache
