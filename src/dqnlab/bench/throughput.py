"""Throughput and memory of the Nature DQN on the machine it runs on.

Figures: replay memory per transition and the resident memory of a filled replay, the time
to sample a minibatch, the update alone (and its GFLOP/s against a dense float32 matrix
multiply's on the same threads, `flops.py`; its time over that of its own dense operations
alone, `dense.py`), training throughput with the nature preset after the replay-start
phase, and evaluation throughput at epsilon 0.05: the final evaluation's (`play_games`,
every core) and the periodic one's (`play`, one environment).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import psutil
import torch

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.cleanrl import CleanRLPeer, cleanrl_figures
from dqnlab.bench.compression import measure_compression
from dqnlab.bench.dense import dense_figures
from dqnlab.bench.flops import matmul_figures, measure_matmul, update_flop_figures, update_flops
from dqnlab.bench.measure import (
    fill_replay,
    machine_figures,
    measure_training,
    median_sample_us,
    median_update_ms,
    random_frames,
)
from dqnlab.bench.peers import peer_round, prepare_peers
from dqnlab.config import Config, resolve_config
from dqnlab.run.lockstep import play_games
from dqnlab.run.play import play
from dqnlab.run.state import TrainingState, replay_device


def _resident_bytes() -> int:
    return psutil.Process().memory_info().rss


def run_benchmark(
    env: str = "breakout",
    steps: int = 2000,
    replay_capacity: int = 1_000_000,
    device: torch.device | None = None,
    seed: int = 0,
    update_repeats: int = 50,
    peers: bool = False,
    rounds: int | None = None,
    peer_learning_starts: int = 5000,
    compile_update: bool = False,
    compression_fill_steps: int = 0,
    compression_checkpoint_capacity: int = 0,
    cleanrl_dir: Path | None = None,
    cleanrl_venv: Path | None = None,
) -> dict[str, Any]:
    """All figures in one run. With `peers`, Stable-Baselines3's DQN is measured in
    `rounds` (default 2) alternating with dqnlab's training, with the same settings. With
    `compression_fill_steps`, the compressed replay's figures on that many transitions of
    the game (`compression.measure_compression`). With `cleanrl_dir`, CleanRL's DQN from
    that checkout joins the rounds too (`cleanrl.run_cleanrl_dqn`)."""
    device = device or torch.device("cpu")
    rounds = rounds or (2 if peers or cleanrl_dir else 1)
    cleanrl = prepare_peers(peers, cleanrl_dir, cleanrl_venv)
    config = resolve_config(
        "nature",
        env=env,
        seed=seed,
        replay_capacity=replay_capacity,
        compile_update=compile_update,
    )
    figures: dict[str, Any] = {
        "env": env,
        **machine_figures(device),
        "replay_capacity": replay_capacity,
        "steps": steps,
        "compile_update": compile_update,
    }
    replay = _filled_replay(config, device, figures)
    training = TrainingState(config, device, replay=replay)
    figures.update(_update_figures(training, update_repeats))
    figures.update(_training_figures(training, steps, rounds, peer_learning_starts, peers, cleanrl))
    figures.update(_evaluation_figures(training, steps))
    training.close()
    del replay, training
    if compression_fill_steps:
        figures.update(
            measure_compression(
                env,
                compression_fill_steps,
                steps,
                device,
                seed,
                rounds=3,
                checkpoint_capacity=compression_checkpoint_capacity,
            )
        )
    return figures


def _filled_replay(config: Config, device: torch.device, figures: dict[str, Any]) -> ReplayMemory:
    """The replay with every slot written, its resident size and its sampling time added to
    `figures`."""
    capacity, seed = config.replay_capacity, config.seed
    before = _resident_bytes()
    on_device = replay_device(config, device, (84, 84), np.dtype(np.uint8))
    figures["replay_storage"] = "host" if on_device is None else f"host and {on_device}"
    replay = ReplayMemory(capacity, (84, 84), np.uint8, 4, 32, seed, device=on_device)
    fill_replay(replay, random_frames(replay, np.random.default_rng(seed)), 4)
    figures["replay_resident_bytes"] = _resident_bytes() - before
    figures["replay_bytes_per_transition"] = replay.bytes_per_transition
    figures["replay_resident_bytes_per_transition"] = figures["replay_resident_bytes"] / capacity
    figures["peak_resident_bytes"] = _resident_bytes()
    figures["sample_us"] = median_sample_us(replay, 2000)
    return replay


def _update_figures(training: TrainingState, update_repeats: int) -> dict[str, Any]:
    """The update alone on one sampled minibatch, its FLOPs (counted on a first update),
    its dense operations alone, and the matrix multiply it is held against, measured now
    on the same threads."""
    batch = training.replay.sample()
    flop = update_flops(training.agent, batch)
    update_ms = median_update_ms(training.agent, batch, update_repeats)
    dense = dense_figures("", training.agent, batch, update_ms, update_repeats)
    matmul = measure_matmul(training.agent.device)
    return {
        "update_ms": update_ms,
        **dense,
        **update_flop_figures("", flop, update_ms, matmul),
        **matmul_figures(matmul),
    }


def _training_figures(
    training: TrainingState,
    steps: int,
    rounds: int,
    peer_learning_starts: int,
    peers: bool,
    cleanrl: CleanRLPeer | None,
) -> dict[str, Any]:
    """Training after the replay-start phase, alternating with the peers when asked.
    Measured where epsilon has reached its final 0.1, as for 49 of the 50M steps of a
    Nature run (at the start of the anneal nearly every action is random and skips the
    network)."""
    config = training.config
    training.steps = config.replay_start_steps + config.epsilon_decay_steps
    for _ in range(100):
        training.advance()
    train_runs, peer_runs, cleanrl_runs = [], [], []
    for _ in range(rounds):
        train_runs.append(measure_training(training, steps))
        # The peers' ε reaches 0.1 by the end of their replay start: measured alike.
        sb3_run, cleanrl_run = peer_round(
            config, steps, peer_learning_starts, training.agent.device, peers, cleanrl
        )
        peer_runs += [sb3_run] if sb3_run else []
        cleanrl_runs += [cleanrl_run] if cleanrl_run else []
    figures: dict[str, Any] = {
        "train_frames_per_second": float(np.mean([run[0] for run in train_runs])),
        "train_frames_per_second_runs": [round(run[0], 1) for run in train_runs],
    }
    for name, fraction in train_runs[-1][1].items():
        figures[f"train_split_{name}"] = fraction
    if peer_runs:
        figures.update(_sb3_figures(peer_runs, figures["train_frames_per_second"]))
    if cleanrl_runs:
        figures.update(cleanrl_figures(cleanrl_runs, [run[0] for run in train_runs]))
    return figures


def _sb3_figures(peer_runs: list[dict[str, Any]], train_frames_per_second: float) -> dict[str, Any]:
    """Stable-Baselines3's mean frames/s over the rounds, each round's, the last round's
    settings and dqnlab's ratio to it."""
    peer_fps = [run["peer_train_frames_per_second"] for run in peer_runs]
    figures = {k: v for k, v in peer_runs[-1].items() if k.startswith("peer")}
    figures["peer_train_frames_per_second"] = float(np.mean(peer_fps))
    figures["peer_train_frames_per_second_runs"] = [round(f, 1) for f in peer_fps]
    figures["train_ratio_vs_peer"] = train_frames_per_second / float(np.mean(peer_fps))
    return figures


def _evaluation_figures(training: TrainingState, steps: int) -> dict[str, Any]:
    """Evaluation at epsilon 0.05, both for `steps` agent steps: the final protocol's
    games on every core (as `dqnlab evaluate` plays them, cut when the steps are spent),
    and the periodic evaluation's single environment. Worker start-up is not timed."""
    config, agent = training.config, training.agent
    final = play_games(
        agent, config, config.final_eval_episodes, config.seed, epsilon=config.eval_epsilon,
        max_episode_frames=config.final_eval_max_episode_frames, max_steps=steps,
    )  # fmt: skip
    single = play(agent, training.eval_env, 4, config.eval_epsilon, max_steps=steps)
    return {
        "eval_frames_per_second": final.frames_per_second,
        "eval_envs": final.num_envs,
        "eval_workers": final.workers,
        "eval_frames_per_second_single": single.frames_per_second,
    }
