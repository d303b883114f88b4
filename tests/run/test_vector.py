"""Many environments, one learner (`num_envs`): each environment's frames stay in its own
replay stream, the algorithm's periods stay counted in agent steps, every environment's
games are played and logged, and bad values are refused in one line."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab.algorithm.agent import Agent, epsilon_at
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError, ResourceError
from dqnlab.run import state as state_module
from dqnlab.run.rundir import episodes_path, prepare_run_dir
from dqnlab.run.state import TrainingState
from dqnlab.run.train import train

CPU = torch.device("cpu")


def mark(observation: np.ndarray, env: int) -> np.ndarray:
    """The observation with its environment planted in its first element."""
    observation = observation.copy()
    observation.reshape(-1)[0] = 100 + env
    return observation


def plant_env_ids(state: TrainingState) -> None:
    for index, env in enumerate(state.envs):
        step, reset = env.step, env.reset

        def planted_step(action: int, index: int = index, step=step):  # type: ignore[no-untyped-def]
            observation, reward, terminated, truncated = step(action)
            return mark(observation, index), reward, terminated, truncated

        def planted_reset(new_game: bool = False, index: int = index, reset=reset):  # type: ignore[no-untyped-def]
            return mark(reset(new_game), index)

        env.step, env.reset = planted_step, planted_reset  # type: ignore[method-assign]
        history = state.histories[index]
        history.frames[-1] = mark(history.frames[-1], index)


def assert_no_history_mixes_environments(state: TrainingState, draws: int = 20) -> None:
    replay = state.replay
    segment = replay.streams.segment
    for _ in range(draws):
        batch = replay.sample(state.steps)
        assert batch.indices is not None
        frames = np.concatenate(
            [np.asarray(batch.observations), np.asarray(batch.next_observations)], axis=1
        )
        firsts = frames.reshape(*frames.shape[:2], -1)[:, :, 0]
        for row, index in enumerate(batch.indices):
            env = int(index) // segment  # the stream the transition was drawn from
            assert set(firsts[row].tolist()) <= {0, 100 + env}, (index, firsts[row])


def vector_config(base: Config, **changes) -> Config:
    settings = {
        "num_envs": 3, "replay_capacity": 600, "replay_start_steps": 60,
        "target_update_steps": 30, "update_period_steps": 4, "eval_period_steps": 1000,
    }  # fmt: skip
    settings.update(changes)
    return dataclasses.replace(base, **settings)


def test_cartpole_histories_never_mix_two_environments(cartpole) -> None:
    state = TrainingState(vector_config(cartpole), CPU)
    plant_env_ids(state)
    games = []
    while state.steps < 900:  # each 200-slot ring filled and overwritten
        games += state.advance()
    assert state.steps == 900 and all(env.frames == 300 for env in state.envs)
    assert state.replay.streams.writes[0] >= 300 and state.replay.size == 600
    assert_no_history_mixes_environments(state)
    assert {game.env for game in games} == {0, 1, 2}  # every environment plays its games
    for index in range(3):
        played = sum(game.steps for game in games if game.env == index)
        assert played + state.game_steps[index] == 300
    state.close()


@pytest.mark.parametrize(
    "changes",
    [
        {"n_step": 3, "replay_sampling": "prioritized", "replay_compression": "none"},
        {"n_step": 2, "replay_compression": "lz4", "replay_sampling": "prioritized"},
    ],
)
def test_atari_histories_never_mix_two_environments(pong, changes) -> None:
    config = vector_config(pong, replay_capacity=3 * 64, replay_start_steps=30, **changes)
    state = TrainingState(config, CPU)
    plant_env_ids(state)
    while state.steps < 300:
        state.advance()
    assert state.replay.compressed == (changes["replay_compression"] == "lz4")
    assert_no_history_mixes_environments(state)
    state.close()


@pytest.mark.parametrize(("num_envs", "total"), [(3, 121), (8, 120), (2, 120)])
def test_updates_and_target_copies_are_counted_in_agent_steps(
    cartpole, monkeypatch, num_envs, total
) -> None:
    updated, synced = [], []
    original_update = Agent.update
    config = vector_config(cartpole, num_envs=num_envs, replay_start_steps=20)
    state = TrainingState(config, CPU)

    def update(self, batch):  # type: ignore[no-untyped-def]
        updated.append(state.steps)
        return original_update(self, batch)

    monkeypatch.setattr(Agent, "update", update)
    monkeypatch.setattr(Agent, "sync_target", lambda self: synced.append(state.steps))
    calls = 0
    while state.steps < total:
        state.advance(total - state.steps)
        calls += 1
    assert state.steps == total and calls == -(-total // num_envs)  # the last one short
    assert updated == list(range(24, total + 1, 4))  # one update per 4 agent steps, any N
    assert synced == list(range(30, total + 1, 30))
    state.close()


def test_epsilon_follows_each_agent_steps_schedule(cartpole) -> None:
    config = vector_config(cartpole, num_envs=4, replay_start_steps=8, epsilon_decay_steps=16)
    state = TrainingState(config, CPU)
    seen = []
    original = state.agent.act_batch

    def act_batch(observations, epsilons, training=False):  # type: ignore[no-untyped-def]
        seen.extend(epsilons)
        return original(observations, epsilons, training)

    state.agent.act_batch = act_batch  # type: ignore[method-assign]
    for _ in range(8):
        state.advance()
    # Agent step s acts with the ε of s - 1 steps done, as one environment would.
    assert seen == [epsilon_at(step - 1, config) for step in range(1, 33)]
    assert len(set(seen)) > 10 and state.epsilon == seen[-1]
    state.close()


def test_a_run_logs_every_environments_games(tmp_path: Path) -> None:
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=1000, replay_start_steps=200, num_envs=3,
        replay_capacity=900, eval_period_steps=500, eval_steps=200, seed=2,
    )  # fmt: skip
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)
    result = train(config, run, CPU, progress=False, tensorboard=False)
    assert result.steps == 1000 and result.frames == 1000
    with episodes_path(run).open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) > 20
    steps = [int(row["step"]) for row in rows]
    assert steps == sorted(steps) and steps[-1] <= 1000
    assert sum(int(row["steps"]) for row in rows) <= 1000
    # The rows say which environment played: each stepped 1000 / 3 times, so the games
    # of one environment cannot hold more steps than that (all of them together could).
    assert {row["env"] for row in rows} == {"0", "1", "2"}
    for env in "012":
        assert sum(int(row["steps"]) for row in rows if row["env"] == env) <= 334
    # Periods at the agent-step boundaries they cross: 501 and 1000 (vector steps of 3).
    assert [e[0] for e in result.evaluations] == [501, 1000]


def test_bad_num_envs_are_refused_in_one_line(cartpole, monkeypatch) -> None:
    with pytest.raises(ConfigError, match=r"^num_envs = 0 must be positive$"):
        dataclasses.replace(cartpole, num_envs=0)
    with pytest.raises(ConfigError, match=r"^num_envs = 1000 leaves 2 replay slots"):
        dataclasses.replace(cartpole, num_envs=1000, replay_capacity=2000)

    class Memory:
        available = 100 * 2**20  # 100 MiB: 4 MiB an environment allows fewer than 50

    monkeypatch.setattr(state_module.psutil, "virtual_memory", lambda: Memory)
    with pytest.raises(ResourceError, match=r"^num_envs = 50: .* lower num_envs$"):
        TrainingState(vector_config(cartpole, num_envs=50, replay_capacity=5000), CPU)
