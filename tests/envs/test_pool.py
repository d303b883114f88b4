"""Environments in lockstep: the statuses each step reports, in-process and in workers."""

from __future__ import annotations

import multiprocessing

import numpy as np

from dqnlab.envs.pool import (
    FINISHED,
    NEW_EPISODE,
    NEXT_GAME,
    RUNNING,
    EnvGroup,
    EnvWorkers,
    Lockstep,
    _worker,
)

CAP = 12  # CartPole steps per game at most (its frames are steps)


def test_lockstep_arrays_are_views_of_the_buffers() -> None:
    layout = Lockstep.layout(3, (4,), np.dtype(np.float32))
    buffers = Lockstep.buffers(layout)
    lockstep = Lockstep.over(buffers, layout)
    assert lockstep.observations.shape == (3, 4) and lockstep.observations.dtype == np.float32
    lockstep.actions[2] = 7
    assert np.frombuffer(buffers["actions"], dtype=np.int64)[2] == 7


def _statuses(stepper, lockstep: Lockstep, steps: int) -> list[list[int]]:
    """The statuses of every environment after each step, acting 0 (all in one batch)."""
    stepper.start()
    seen = []
    for _ in range(steps):
        lockstep.actions[:] = 0
        stepper.submit(0)
        stepper.wait()
        seen.append(lockstep.statuses.tolist())
    return seen


def test_games_end_at_their_cap_and_environments_stop_when_done(cartpole) -> None:
    layout = Lockstep.layout(2, (4,), np.dtype(np.float32))
    lockstep = Lockstep.over(Lockstep.buffers(layout), layout)
    games = [2, 1]  # environment 0 plays two games, environment 1 one
    with EnvGroup(cartpole, CAP, [0, 1], [5, 6], games, [range(2)], lockstep) as group:
        seen = _statuses(group, lockstep, 2 * CAP + 3)
        frames = lockstep.frames.tolist()
    # Pushing left always, a pole falls within a few steps: read where each game ended.
    next_game = [t for t, row in enumerate(seen) if row[0] == NEXT_GAME]
    finished = {
        env: next(t for t, row in enumerate(seen) if row[env] == FINISHED) for env in (0, 1)
    }
    assert len(next_game) == 1 and next_game[0] < finished[0]
    assert all(row[0] == RUNNING for row in seen[: next_game[0]])
    assert all(row[1] == RUNNING for row in seen[: finished[1]])
    # A finished environment is not stepped again: its status and frames stay.
    assert all(row[env] == FINISHED for env in (0, 1) for row in seen[finished[env] :])
    assert frames == [finished[0] + 1, finished[1] + 1]  # a frame per step, no no-ops
    assert NEW_EPISODE not in {status for row in seen for status in row}


def test_worker_processes_step_as_the_player_would(cartpole) -> None:
    layout = Lockstep.layout(3, (4,), np.dtype(np.float32))
    lockstep = Lockstep.over(Lockstep.buffers(layout), layout)
    seeds, games = [1, 2, 3], [2, 2, 2]
    with EnvGroup(cartpole, CAP, range(3), seeds, games, [range(3)], lockstep) as group:
        expected = _statuses(group, lockstep, 30)
        expected_observations = lockstep.observations.copy()
    with EnvWorkers(cartpole, CAP, seeds, games, [range(3)], layout, workers=2) as workers:
        assert _statuses(workers, workers.lockstep, 30) == expected
        assert np.array_equal(workers.lockstep.observations, expected_observations)


def test_a_worker_whose_player_is_gone_ends_quietly(cartpole) -> None:
    # A killed `dqnlab evaluate` leaves its workers a closed pipe: they return, without
    # the traceback of a BrokenPipeError on the terminal.
    layout = Lockstep.layout(1, (4,), np.dtype(np.float32))
    arguments = {
        "config": cartpole, "max_episode_frames": CAP, "env_ids": [0], "seeds": [1],
        "games": [1], "batches": [range(1)],
    }  # fmt: skip
    player_end, worker_end = multiprocessing.Pipe()
    player_end.close()
    _worker(worker_end, arguments, Lockstep.buffers(layout), layout)  # returns, no raise
