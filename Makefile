# Everyday commands. Each target installs what it needs into .venv first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
GAME ?= pong
ARGS ?=

.PHONY: install install-test train test test-slow lint format typecheck clean
.PHONY: install-docs docs docs-serve bench-gpu bench-table

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .

install-test: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test]"

install-docs: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[docs]"

# The main job: the Nature DQN on an Atari game (GAME=breakout, ARGS="--seed 1" ...).
train: install
	$(BIN)/dqnlab train --env $(GAME) --preset nature $(ARGS)

# The test suite CI runs: lint, format and type checks, then every test not marked slow.
test: install-test
	$(BIN)/ruff check src tests docs examples scripts
	$(BIN)/ruff format --check src tests docs examples scripts
	$(BIN)/mypy src scripts
	$(BIN)/python -m pytest -q

# Slow tests (minutes): the classic preset solves CartPole-v1 for 3 seeds, and so does each
# part of the DQN family and the example variant; the sweep on Ray clusters on 127.0.0.1
# (lost node, killed driver, Ctrl-C, auto and ray://).
test-slow: install-test
	$(BIN)/python -m pytest -q -m slow

lint: install-test
	$(BIN)/ruff check src tests docs examples scripts
	$(BIN)/ruff format --check src tests docs examples scripts

format: install-test
	$(BIN)/ruff format src tests docs examples scripts
	$(BIN)/ruff check --fix src tests docs examples scripts

typecheck: install-test
	$(BIN)/mypy src scripts

# The documentation site, into site/: the settings and command references are generated from
# the code (docs/hooks.py); --strict fails on any warning (a broken link or anchor, a page
# left out of the navigation).
docs: install-docs
	$(BIN)/mkdocs build --strict --site-dir site

# The site served on this machine only, rebuilt as docs/ changes.
docs-serve: install-docs
	$(BIN)/mkdocs serve -a 127.0.0.1:8000

# The GPU path's figures into bench-gpu.json (under 8 minutes on one H100/H200; see
# docs/benchmark.md). ARGS="--device cpu --quick" runs it on CPU in seconds.
bench-gpu: install
	$(BIN)/dqnlab bench gpu --json bench-gpu.json $(ARGS)

# Issue 22's CPU table in one command, into bench-table.json (about 15 minutes on 2 cores):
# training frames/s with num_envs 1, 2, 4, 8, each sequential and with an actor thread,
# Stable-Baselines3 and (CLEANRL=path/to/a/CleanRL/checkout) CleanRL's dqn_atari.py in the
# same alternating rounds, the update against a matrix multiply, the stop checkpoint.
CLEANRL ?=
bench-table: install
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/dqnlab bench envs --num-envs 1,2,4,8 --concurrency none,actor-learner --peers \
		--checkpoint --steps 1000 --replay-capacity 100000 --json bench-table.json \
		$(if $(CLEANRL),--cleanrl $(CLEANRL)) $(ARGS)

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache .ruff_cache .mypy_cache
	rm -rf site
