"""Acting while learning (`concurrency = "actor-learner"`): the threaded run is a function
of the seed alone, whatever the threads' timing; it equals a reference written here on the
sequential `TrainingState` with the actor's network lag added; the replay ratio is
Nature's; a killed run resumes bit for bit; bad settings are refused in one line."""

from __future__ import annotations

import copy
import dataclasses
import random
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from dqnlab.algorithm.agent import Agent
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.concurrent import ActorLearnerState, actor_seed
from dqnlab.run.state import FinishedGame, TrainingState
from tests.run.test_resume import (
    CARTPOLE,
    assert_identical,
    csv_rows,
    dqnlab,
    finish,
    train_killed_and_resumed,
    wait_for_checkpoint,
)
from tests.run.test_vector_resume import final_state

CPU = torch.device("cpu")


def small(cartpole: Config, **changes: Any) -> Config:
    settings: dict[str, Any] = {
        "concurrency": "actor-learner", "replay_start_steps": 100, "replay_capacity": 900,
        "target_update_steps": 50, "total_steps": 500, "seed": 4, "epsilon_decay_steps": 150,
    }  # fmt: skip
    settings.update(changes)
    return dataclasses.replace(cartpole, **settings)


def play_out(state: TrainingState) -> list[FinishedGame]:
    games: list[FinishedGame] = []
    while state.steps < state.config.total_steps:
        games += state.advance(state.config.total_steps - state.steps)
    return games


def jitter(state: TrainingState, seed: int, actor_seconds: float, learner_seconds: float) -> None:
    """Sleeps of random length in the emulators and the update: another interleaving."""
    rng = random.Random(seed)
    for env in state.envs:
        step = env.step

        def slow_step(action: int, step=step):  # type: ignore[no-untyped-def]
            time.sleep(rng.uniform(0, actor_seconds))
            return step(action)

        env.step = slow_step  # type: ignore[method-assign]
    update = state.agent.update

    def slow_update(batch):  # type: ignore[no-untyped-def]
        time.sleep(rng.uniform(0, learner_seconds))
        return update(batch)

    state.agent.update = slow_update  # type: ignore[method-assign]


def lagged_reference(config: Config) -> TrainingState:
    """The semantics written out on the sequential loop: the actor's generator and noise,
    and the network after the last multiple of K at least K updates back."""
    state = TrainingState(config, CPU)
    agent, refresh = state.agent, config.actor_refresh_updates
    acting = copy.copy(agent)
    acting.rng = np.random.default_rng(actor_seed(config))
    acting.noise_generator = torch.Generator(device=CPU)
    acting.noise_generator.manual_seed(actor_seed(config))
    copies = {0: copy.deepcopy(agent.online)}
    update = agent.update

    def update_and_copy(batch):  # type: ignore[no-untyped-def]
        result = update(batch)
        if agent.updates % refresh == 0:
            copies[agent.updates] = copy.deepcopy(agent.online)
        return result

    def lagged() -> Agent:
        acting.online = copies[max(0, (agent.updates // refresh - 1) * refresh)]
        return acting

    agent.update = update_and_copy  # type: ignore[method-assign]
    agent.act = lambda obs, eps, training=False: Agent.act(lagged(), obs, eps, training)  # type: ignore[method-assign]
    agent.act_batch = lambda obs, eps, training=False: Agent.act_batch(  # type: ignore[method-assign]
        lagged(), obs, eps, training
    )
    state.acting = acting  # type: ignore[attr-defined]
    return state


def assert_same_learning(a: TrainingState, b: TrainingState) -> None:
    for part in ("online", "target"):
        for (name, x), y in zip(
            getattr(a.agent, part).state_dict().items(),
            getattr(b.agent, part).state_dict().values(),
            strict=True,
        ):
            assert torch.equal(x, y), f"{part}.{name}"
    assert_identical(a.agent.optimizer.state_dict(), b.agent.optimizer.state_dict(), "optimizer")
    for key, array in a.replay.arrays.items():
        assert np.array_equal(array, b.replay.arrays[key]), key
    assert a.agent.updates == b.agent.updates
    assert a.acting.rng.bit_generator.state == b.acting.rng.bit_generator.state  # type: ignore[attr-defined]


CASES = {
    "one env, K=1": {"num_envs": 1, "actor_refresh_updates": 1},
    "three envs, K=3": {"num_envs": 3, "actor_refresh_updates": 3},
    "two envs, noisy, K=2": {
        "num_envs": 2, "actor_refresh_updates": 2, "noisy": True, "epsilon_start": 0.0,
        "epsilon_end": 0.0,
    },
}  # fmt: skip


@pytest.mark.parametrize("case", list(CASES))
def test_threads_equal_the_sequential_semantics_bit_for_bit(cartpole, case: str) -> None:
    config = small(cartpole, **CASES[case])
    reference = lagged_reference(config)
    reference_games = play_out(reference)
    sequential = ActorLearnerState(config, CPU, threaded=False)
    assert play_out(sequential) == reference_games
    assert_same_learning(sequential, reference)
    # Slow emulators, then a slow learner: the actor far behind, then far ahead.
    for seed, actor_seconds, learner_seconds in ((1, 0.002, 0.0), (2, 0.0, 0.004)):
        threaded = ActorLearnerState(config, CPU)
        jitter(threaded, seed, actor_seconds, learner_seconds)
        assert play_out(threaded) == reference_games
        threaded.close()
        assert_same_learning(threaded, reference)
    assert reference.agent.updates > 3 * config.actor_refresh_updates  # the lag mattered
    sequential.close()


def test_the_lag_changes_the_actions(cartpole) -> None:
    """Not the sequential loop under another name: the same seed acts otherwise."""
    config = small(cartpole, num_envs=1, actor_refresh_updates=1, epsilon_end=0.0)
    concurrent = ActorLearnerState(config, CPU, threaded=False)
    ordinary = TrainingState(dataclasses.replace(config, concurrency="none"), CPU)
    play_out(concurrent), play_out(ordinary)
    assert not np.array_equal(
        concurrent.replay.arrays["actions"], ordinary.replay.arrays["actions"]
    )


def test_each_update_samples_the_transitions_up_to_its_own_step(cartpole) -> None:
    config = small(cartpole, num_envs=3, actor_refresh_updates=2, total_steps=600)
    state = ActorLearnerState(config, CPU)
    stored, seen = [0], []
    add, update = state.replay.add, state.agent.update

    def counted_add(*args, **kwargs):  # type: ignore[no-untyped-def]
        stored[0] += 1
        return add(*args, **kwargs)

    def noted_update(batch):  # type: ignore[no-untyped-def]
        seen.append((state.steps, stored[0]))
        return update(batch)

    state.replay.add = counted_add  # type: ignore[method-assign]
    state.agent.update = noted_update  # type: ignore[method-assign]
    jitter(state, 3, 0.0, 0.002)  # the actor runs ahead
    play_out(state)
    state.close()
    period, start = config.update_period_steps, config.replay_start_steps
    assert [step for step, _ in seen] == list(range(start + period, 601, period))
    # As the sequential loop: a round's three transitions stored, then its steps learned.
    assert all(adds == -(-step // 3) * 3 for step, adds in seen)
    assert state.agent.updates == (config.total_steps - start) // period


def test_a_state_saved_with_rounds_pending_carries_on_exactly(cartpole) -> None:
    """The actor ahead when the state is saved: its rounds not yet learned from, its
    emulators and its network copies come back, and the run goes on as if unbroken."""
    config = small(cartpole, num_envs=2, actor_refresh_updates=2)
    reference = ActorLearnerState(config, CPU, threaded=False)
    reference_games = play_out(reference)
    first = ActorLearnerState(config, CPU)
    games: list[FinishedGame] = []
    while first.steps < 300:
        games += first.advance()
    deadline = time.monotonic() + 10  # the actor runs ahead while the learner waits
    while not first.pending and time.monotonic() < deadline:
        time.sleep(0.01)
    saved = copy.deepcopy(first.state_dict())
    assert saved["actor"]["pending"] and saved["actor"]["steps"] > first.steps
    first.close()
    second = ActorLearnerState(config, CPU)
    for name, array in first.replay.arrays.items():  # saved beside the state, chunk by chunk
        second.replay.arrays[name][...] = array
    second.load_state_dict(saved)
    games += play_out(second)
    second.close()
    assert games == reference_games
    assert_same_learning(second, reference)


def test_bad_settings_are_refused_in_one_line(cartpole) -> None:
    cases = {
        "concurrency": {"concurrency": "threads"},
        "actor_refresh_updates": {"concurrency": "actor-learner", "actor_refresh_updates": 0},
        "update_graph": {"concurrency": "actor-learner", "update_graph": "cuda"},
    }
    for name, changes in cases.items():
        with pytest.raises(ConfigError, match=name) as error:
            dataclasses.replace(cartpole, **changes)
        assert "\n" not in str(error.value)


AL = ["--set", "concurrency=actor-learner", "--set", "actor_refresh_updates=2"]
RESUMED = {
    "one env": [*CARTPOLE, *AL],
    "three envs": [*CARTPOLE, *AL, "--set", "num_envs=3", "--steps", "3001",
                   "--set", "replay_capacity=2100"],
    # Both ways off the training thread at once: the actor, and the periodic evaluation
    # in a worker process (its results pending in the checkpoints the kills fall on).
    "background evaluations": [*CARTPOLE, *AL, "--set", "periodic_eval=background"],
}  # fmt: skip


def assert_same_run(reference: Path, resumed: Path) -> None:
    state_a, replay_a = final_state(reference)
    state_b, replay_b = final_state(resumed)
    if 'periodic_eval = "background"' in (reference / "config.toml").read_text():
        # Background evaluations play on environments of their own: the training process's
        # evaluation environment is never reset, so its state is not the run's.
        del state_a["learner"]["eval_env"], state_b["learner"]["eval_env"]
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(state_a["run"], state_b["run"], "run")
    assert_identical(replay_a, replay_b, "replay")
    timing = ("wall_seconds", "frames_per_second")
    for name in ("episodes.csv", "evaluations.csv"):
        assert csv_rows(reference / name, timing) == csv_rows(resumed / name, timing), name


@pytest.mark.parametrize(
    "name",
    # "background evaluations" is one environment with the actor too: "one env" alone runs
    # under the slow marker, for CI's time, and so does "three envs" (several environments
    # with the actor: test_threads_equal_the_sequential_semantics_bit_for_bit).
    [pytest.param(name, marks=pytest.mark.slow) if name in ("one env", "three envs") else name
     for name in RESUMED],
)  # fmt: skip
def test_a_killed_actor_learner_run_resumes_bit_for_bit(tmp_path: Path, name: str) -> None:
    args = RESUMED[name]
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    kills = train_killed_and_resumed(args, reference, resumed, most_kills=2, latest_kill=0.5)
    assert kills >= 1, "the run was too fast to be killed"
    assert_same_run(reference, resumed)


def test_a_stop_signal_saves_the_actor_between_rounds_and_resumes(tmp_path: Path) -> None:
    args = RESUMED["three envs"]
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(dqnlab("train", *args, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = dqnlab("train", *args, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=0)
    process.send_signal(signal.SIGTERM)
    code, stderr = finish(process)
    assert code == 143, stderr
    code, stderr = finish(dqnlab("resume", str(resumed), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert_same_run(reference, resumed)


# Five seeds each way, so that one unlucky seed neither fails the test nor hides a real
# difference (until 2026-12-05 this was three seeds alone with seed 1 an expected failure:
# its best network scored 401.9 ± 120.1 over 20 games where the sequential loop's scored 500).
COMPARED_SEEDS = range(5)


def _cartpole_score(tmp_path: Path, seed: int, concurrency: str) -> float:
    """The best network's mean over 20 games of the classic preset on CartPole-v1."""
    from dqnlab.run.evaluate import final_evaluation
    from dqnlab.run.rundir import prepare_run_dir
    from dqnlab.run.train import train

    config = resolve_config("classic", env="CartPole-v1", seed=seed, concurrency=concurrency)
    run = tmp_path / f"cartpole-{concurrency}-{seed}"
    prepare_run_dir(run, force=False)
    trained = train(config, run, CPU, progress=False, tensorboard=False)
    assert trained.steps == config.total_steps
    result, _ = final_evaluation(run, "best", 20, seed=1000 + seed, device=CPU)
    return result.mean


@pytest.mark.slow
def test_acting_while_learning_learns_cartpole_as_the_sequential_loop_does(tmp_path: Path) -> None:
    """The classic preset with an actor thread (K = 4) against the sequential loop, five seeds
    each: the actor-learner's scores are not stochastically lower (one-sided Mann-Whitney U,
    5%: with five against five it detects a shift that puts most of its scores below the
    sequential ones), and most of its seeds solve CartPole (>= 475 over 20 games)."""
    from scipy.stats import mannwhitneyu

    scores = {
        concurrency: [_cartpole_score(tmp_path, seed, concurrency) for seed in COMPARED_SEEDS]
        for concurrency in ("none", "actor-learner")
    }
    print({name: [round(score, 1) for score in values] for name, values in scores.items()})
    sequential, actor_learner = scores["none"], scores["actor-learner"]
    test = mannwhitneyu(actor_learner, sequential, alternative="less")
    print(f"one-sided Mann-Whitney U: p = {test.pvalue:.3f}")
    assert test.pvalue >= 0.05
    assert sum(score >= 475 for score in actor_learner) >= 4
