"""Helpers shared by test modules (fixtures are in conftest.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

from dqnlab.algorithm.agent import Agent, build_agent
from dqnlab.cli import main
from dqnlab.config import Config
from dqnlab.envs import make_env

AGENT_SEED = 7


def untrained_agent(config: Config) -> Agent:
    """The same small untrained network and acting stream at every call."""
    torch.manual_seed(0)
    env = make_env(config, training=False, seed=0)
    agent = build_agent(config, env, torch.device("cpu"), AGENT_SEED)
    env.close()
    return agent


class BlinkEnv(gym.Env):
    """Renders 21x33 RGB frames (odd sizes) in solid blocks that change every step; a game
    lasts 5 to 9 steps, the reward is the action."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, render_mode: str | None = None) -> None:
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.t = 0
        self.length = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        self.length = int(self.np_random.integers(5, 10))
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.full(2, self.t / 10, np.float32), float(action), self.t >= self.length, False, {}

    def render(self) -> np.ndarray:
        frame = np.zeros((21, 33, 3), np.uint8)
        frame[:10, :16] = (40 * self.t % 256, 200, 30)
        frame[10:, 16:] = (250, 20 * self.t % 256, 120)
        return frame


class RunsCode:
    """Unpickling this object runs code: it creates the file `marker`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (exec, (f"open({str(self.marker)!r}, 'w').close()",))


def dqnlab_main(capsys: pytest.CaptureFixture[str], monkeypatch, *args: str) -> tuple[int, str]:  # noqa: ANN001
    """`dqnlab ARGS` in this process (no interpreter start-up): its exit status and stderr."""
    monkeypatch.setattr(sys, "argv", ["dqnlab", *args])
    with pytest.raises(SystemExit) as exit_info:
        main()
    return int(exit_info.value.code or 0), capsys.readouterr().err


def dqnlab(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """`dqnlab ARGS` as a user runs it: a new process, its output captured."""
    return subprocess.run(
        [sys.executable, "-m", "dqnlab", *args],
        capture_output=True, text=True, cwd=cwd, timeout=600,
    )  # fmt: skip
