"""Fixtures shared by the test modules (shared helper functions are in helpers.py)."""

from __future__ import annotations

import pytest

from dqnlab.config import Config, resolve_config
from dqnlab.run.determinism import warm_up_vector_math


@pytest.fixture(scope="session", autouse=True)
def _vector_math_warmed_up() -> None:
    """MKL's vector math called once in every thread before any test computes, as a run
    does at its start (`warm_up_vector_math`): a test that compares two computations made
    in this process would otherwise see the first one come out wrong now and then."""
    warm_up_vector_math()


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
