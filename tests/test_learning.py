"""Learning tests (slow, `make test-slow`): the classic preset solves CartPole-v1, with each
part of the DQN family too, and reaches the optimal score of environments whose
observations are not vectors.

Solved means the run's best network scores a mean of at least 475 over 20 evaluation
games (the Gymnasium threshold), within the preset's budget of at most 100k steps.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.evaluate import final_evaluation
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.train import train


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_classic_preset_solves_cartpole(tmp_path: Path, seed: int) -> None:
    config = resolve_config("classic", env="CartPole-v1", seed=seed)
    assert config.total_steps <= 100_000
    run = tmp_path / f"cartpole-{seed}"
    prepare_run_dir(run, force=False)
    trained = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    result, _ = final_evaluation(run, "best", 20, seed=1000 + seed, device=torch.device("cpu"))
    first_solved = next((step for step, mean in trained.evaluations if mean >= 475), None)
    print(f"seed {seed}: first periodic evaluation >= 475 at step {first_solved}; "
          f"final 20 games {result.mean:.1f} ± {result.std:.1f}")  # fmt: skip
    assert len(result.scores) == 20
    assert result.mean >= 475


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_eight_environments_solve_cartpole_as_one_does(tmp_path: Path, seed: int) -> None:
    """num_envs = 8 on the classic preset's budget (in agent steps summed over the eight):
    the same score as the single-environment test above."""
    config = resolve_config("classic", env="CartPole-v1", seed=seed, num_envs=8)
    run = tmp_path / f"cartpole-8-envs-{seed}"
    prepare_run_dir(run, force=False)
    trained = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    result, _ = final_evaluation(run, "best", 20, seed=1000 + seed, device=torch.device("cpu"))
    first_solved = next((step for step, mean in trained.evaluations if mean >= 475), None)
    print(f"8 envs, seed {seed}: first periodic evaluation >= 475 at step {first_solved}; "
          f"final 20 games {result.mean:.1f} ± {result.std:.1f}")  # fmt: skip
    assert trained.steps == config.total_steps
    assert result.mean >= 475


# Each part of the DQN family on top of the classic preset (its learning settings, which
# solve CartPole-v1), and the example variant: each must solve it too. C51's support
# covers CartPole's returns (at most 1 / (1 - 0.99) = 100 with a reward of 1 per step).
CARTPOLE_C51 = {"distributional": "c51", "distributional_v_min": 0.0, "distributional_v_max": 100.0}
VARIANTS = {
    "double": {"target": "double"},
    "dueling": {"dueling": True},
    "prioritized": {"replay_sampling": "prioritized"},
    "n_step": {"n_step": 3},
    "c51": CARTPOLE_C51,
    "noisy": {"noisy": True, "epsilon_start": 0.0, "epsilon_end": 0.0},
    "rainbow": {
        **CARTPOLE_C51, "target": "double", "dueling": True, "noisy": True, "n_step": 3,
        "replay_sampling": "prioritized", "priority_exponent": 0.5, "epsilon_start": 0.0,
        "epsilon_end": 0.0, "max_gradient_norm": 10.0,
    },
    "munchausen": {"loss": "examples.munchausen:MunchausenLoss"},
    # The shipped quantile parts: QR-DQN at its own default (200 quantiles).
    "qrdqn": {
        "head": "dqnlab.algorithm.quantile:quantile_head",
        "loss": "dqnlab.algorithm.quantile:QuantileLoss",
    },
    # IQN with N = N' = K = 8 fractions, not its Atari defaults (N = N' = 64, K = 32). At
    # the defaults, seed 0 never reached 475 in a periodic evaluation (final 20 games
    # 206.5 ± 54.5, about an hour of CPU); the head and loss match Dopamine's agent, so
    # the settings are changed, not the code. With N = N' = K = 8 (measured 2026-12-04,
    # OMP_NUM_THREADS=1; each run stopped at its first periodic 500, after which best.pt
    # no longer changes) the first evaluation of 500 came at step 30k for seed 0 (10 min
    # of CPU), 35k for seed 1 and 40k for seed 2, best.pt scoring 500.0 ± 0.0 over 20
    # games each time; N = N' = 8 with K = 32 reached 500 at 45k (seed 0). Whether N = 64
    # fails by its size or by chance was not measured (a run costs hours of CPU): eight
    # fractions also cost an eighth of the head's arithmetic, which dominates the run.
    "iqn": {
        "head": "dqnlab.algorithm.quantile:implicit_quantile_head",
        "loss": "dqnlab.algorithm.quantile:ImplicitQuantileLoss",
        "parts": {
            "loss": {"online_samples": 8, "target_samples": 8},
            "head": {"acting_samples": 8},
        },
    },
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_each_variant_solves_cartpole(tmp_path: Path, variant: str) -> None:
    config = resolve_config("classic", env="CartPole-v1", seed=0, **VARIANTS[variant])
    run = tmp_path / variant
    prepare_run_dir(run, force=False)
    trained = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    result, _ = final_evaluation(run, "best", 20, seed=1000, device=torch.device("cpu"))
    first_solved = next((step for step, mean in trained.evaluations if mean >= 475), None)
    print(f"{variant}: first periodic evaluation >= 475 at step {first_solved}; "
          f"final 20 games {result.mean:.1f} ± {result.std:.1f}")  # fmt: skip
    assert result.mean >= 475


# Observation spaces other than a vector (docs/observation-spaces.md), each to its optimal
# score: CliffWalking-v1 (a Discrete observation, one-hot: 13 steps along the cliff, -13;
# no TimeLimit of its own, so capped here), FrozenLake-v1 without slipping (reaching the
# goal: 1) and the nested-Dict cue game of the tests (8).
SPACE_TASKS = {
    "cliffwalking-discrete": (
        "CliffWalking-v1", 30_000, -13.0,
        {"max_episode_frames": 200, "eval_max_episode_frames": 100,
         "final_eval_max_episode_frames": 100},
    ),
    "frozenlake-discrete": (  # with an environment argument: the deterministic lake
        "FrozenLake-v1", 20_000, 1.0, {"env_kwargs": {"is_slippery": False}},
    ),
    "nested-dict": ("tests.envs.space_envs:NestedDictEnv", 20_000, 8.0, {}),
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("task", list(SPACE_TASKS))
def test_structured_observations_reach_their_optimal_score(tmp_path: Path, task: str) -> None:
    env, steps, optimal, settings = SPACE_TASKS[task]
    config = resolve_config(
        "classic", env=env, seed=0, total_steps=steps, eval_period_steps=5000, **settings
    )
    run = tmp_path / task
    prepare_run_dir(run, force=False)
    trained = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    result, _ = final_evaluation(run, "best", 20, seed=1000, device=torch.device("cpu"))
    first = next((step for step, mean in trained.evaluations if mean >= optimal), None)
    print(f"{task}: first periodic evaluation at the optimum ({optimal}) at step {first}; "
          f"final 20 games {result.mean:.2f} ± {result.std:.2f}")  # fmt: skip
    assert result.mean == optimal
