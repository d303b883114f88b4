"""The Nature paper's final evaluation of a run's network: whole games of at most 5 minutes
(`final_eval_max_episode_frames`), at `eval_epsilon`, after random no-op starts, played on
every core (`lockstep.play_games`), and the record `dqnlab evaluate` and reports keep.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from dqnlab.algorithm.agent import Agent
from dqnlab.config import Config
from dqnlab.envs import is_atari, make_env
from dqnlab.errors import DqnlabError
from dqnlab.run import exported, rundir
from dqnlab.run.denormals import apply_denormals
from dqnlab.run.lockstep import play_games
from dqnlab.run.play import EvaluationResult


def final_evaluation_record(
    result: EvaluationResult,
    config: Config,
    checkpoint_path: Path,
    checkpoint_step: int | None,
    seed: int,
    settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The result of a final evaluation as `dqnlab evaluate --json` and
    `final_evaluation.json` hold it (std over games with ddof 0, as numpy's default).
    `checkpoint_step`: the training step of the network played, as its file said when
    it was loaded (a running training may have replaced the file since). `settings`: the
    evaluation settings changed from the run's own (`dqnlab evaluate --set`), recorded
    with their values as played."""
    changed = {name: getattr(config, name) for name in settings or {}}
    return {
        "env": config.env,
        "checkpoint": str(checkpoint_path),
        "checkpoint_step": checkpoint_step,
        "seed": seed,
        "episodes": len(result.scores),
        "epsilon": config.eval_epsilon,
        "max_episode_frames": config.final_eval_max_episode_frames,
        "scores": result.scores,
        "mean": result.mean,
        "std": result.std,
        "frames": result.frames,
        "frames_per_second": result.frames_per_second,
        **({"settings": changed} if changed else {}),
    }


@dataclass
class EvaluatedNetwork:
    """A saved network ready to play, and where it came from."""

    agent: Agent
    config: Config  # the configuration it was trained with
    path: Path
    step: int | None  # the training step at which it was saved
    env_seed: int  # seeds the environments it plays (child 0 of the evaluation's seed)


def load_evaluated_agent(
    run_dir: Path,
    checkpoint: str,
    seed: int,
    device: torch.device,
    settings: dict[str, Any] | None = None,
) -> EvaluatedNetwork:
    """The network `final_evaluation` plays: the agent built from the network file
    ("best", "last" or a file path), playing as its run's configuration says unless
    `settings` change that (`with_evaluation_settings`), and the seed of the evaluation's
    environments (child 0 of `seed`; child 1 seeds the agent)."""
    if checkpoint in ("best", "last"):
        rundir.load_run_config(run_dir)  # a clear error if RUN_DIR is not a run
        path = _run_network_path(run_dir, checkpoint)
    else:
        path = Path(checkpoint)
    if path.suffix == ".safetensors":
        payload = exported.load_network(path, map_location=device)
    else:
        payload = rundir.load_network(path, map_location=device)
    agent, config, env_seed = rundir.agent_from_network(payload, path, seed, device, settings)
    message = unbounded_games_warning(config)
    if message is not None:
        warnings.warn(message, stacklevel=2)
    step = payload.get("step")
    return EvaluatedNetwork(agent, config, path, int(step) if step is not None else None, env_seed)


def _run_network_path(run_dir: Path, checkpoint: str) -> Path:
    """The network `checkpoint` ("best" or "last") of a run directory, or the one network
    of an exported folder (`exported`), which is the network it was exported with."""
    if not exported.is_exported_dir(run_dir):
        return rundir.network_path(run_dir, checkpoint)
    if checkpoint != "best":
        raise DqnlabError(
            f"{run_dir} is an exported folder: its one network is {exported.MODEL_FILE} "
            "(--checkpoint best, the default)"
        )
    return exported.network_path(run_dir)


def unbounded_games_warning(config: Config) -> str | None:
    """Why a final evaluation might never end, or None: a Gymnasium environment with no
    step limit of its own and no `final_eval_max_episode_frames` ends a game only when
    the environment does, which a policy that balances or dithers forever never reaches."""
    if is_atari(config.env) or config.final_eval_max_episode_frames > 0:
        return None
    env = make_env(config, training=False, seed=0)
    try:
        limit = getattr(env, "step_limit", 0)
    finally:
        env.close()
    if limit:
        return None
    return (
        f"{config.env} has no step limit (no TimeLimit) and final_eval_max_episode_frames "
        "is 0: a game the agent never ends never finishes this evaluation (Ctrl-C stops "
        "it); train with --set final_eval_max_episode_frames=N to cap games"
    )


def final_evaluation(
    run_dir: Path,
    checkpoint: str,
    episodes: int | None,
    seed: int,
    device: torch.device,
    *,
    num_envs: int | None = None,
    settings: dict[str, Any] | None = None,
) -> tuple[EvaluationResult, EvaluatedNetwork]:
    """Nature's final protocol on a run's network: whole games of at most
    `final_eval_max_episode_frames`, at `eval_epsilon`, with random no-op starts.

    The games are played by `play_games` on `num_envs` environments in lockstep (None:
    `default_num_envs`), stepped on every core. The network is built from the
    configuration saved in the checkpoint itself, so a checkpoint file from another run
    evaluates with its own settings, except those `settings` change (another protocol for
    the same network: `with_evaluation_settings`).
    """
    if episodes is not None and episodes <= 0:
        raise DqnlabError(f"--episodes {episodes} must be positive")
    if num_envs is not None and num_envs <= 0:
        raise DqnlabError(f"num_envs {num_envs} must be positive")
    network = load_evaluated_agent(run_dir, checkpoint, seed, device, settings)
    config = network.config
    apply_denormals(config)  # the network computes as it did in training
    count = episodes if episodes is not None else config.final_eval_episodes
    result = play_games(
        network.agent,
        config,
        count,
        network.env_seed,
        epsilon=config.eval_epsilon,
        max_episode_frames=config.final_eval_max_episode_frames,
        num_envs=num_envs,
    )
    return result, network


def evaluate_and_save(
    run_dir: Path, checkpoint: str, episodes: int | None, seed: int, device: torch.device
) -> dict[str, Any]:
    """`final_evaluation` of the run's `checkpoint` network, saved as its
    final_evaluation.json (the record returned)."""
    result, network = final_evaluation(run_dir, checkpoint, episodes, seed, device)
    record = final_evaluation_record(result, network.config, network.path, network.step, seed)
    rundir.save_final_evaluation(run_dir, record)
    return record


def final_network(run_dir: Path) -> str:
    """The network a run's final evaluation plays: its `final_eval_network` ("best" or
    "last"); "best" for an exported folder (its one network) or a run whose config cannot
    be read (the error comes when the network is loaded)."""
    if exported.is_exported_dir(run_dir):
        return "best"
    try:
        return rundir.load_run_config(run_dir).final_eval_network
    except DqnlabError:
        return "best"
