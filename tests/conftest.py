"""Fixtures shared by the test modules (shared helper functions are in helpers.py)."""

from __future__ import annotations

import pytest

from dqnlab.config import Config, resolve_config


@pytest.fixture(scope="session")
def cartpole() -> Config:
    """The classic preset on CartPole-v1."""
    return resolve_config("classic", env="CartPole-v1")


@pytest.fixture(scope="session")
def pong() -> Config:
    """The nature preset on Pong."""
    return resolve_config("nature", env="pong")


@pytest.fixture(scope="session")
def nature(pong: Config) -> Config:
    """The nature preset (on Pong), for tests of the update's settings."""
    return pong
