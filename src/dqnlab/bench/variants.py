"""What each member of the DQN family costs on this machine: `dqnlab bench variants`.

Every variant is its shipped preset on the same game, with replays of the same size filled
with the same frames. Per variant: the minibatch draw (for prioritized replay, with the
priority update that follows every update), the update alone (with its GFLOP/s against a
dense float32 matrix multiply's timed right after it; its FLOPs counted by PyTorch's
`FlopCounterMode` on one update, `flops.py`; and its time over that of its own dense
operations alone, `dense.py`), and training frames/s once learning runs, measured in
alternating rounds so that a change in the machine's load falls on every variant alike.
Frames/s are also given as a ratio to the `nature` preset's in the same run (and
prioritized replay's to uniform's), with the share of each timed part of a step
(environment, acting, storing, sampling, update), and the minutes one whole run of the
preset takes here (`_run_minutes`: `variants der,drq_epsilon` gives Atari 100k's minutes
per game). Besides, the prioritized draw and update on a full 1M-slot sum tree: the
replay's part of one prioritized update at Nature's size.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.prioritized import measure_sampling
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.dense import dense_figures
from dqnlab.bench.flops import measure_matmul, update_flop_figures, update_flops
from dqnlab.bench.measure import (
    call_seconds,
    fill_replay,
    machine_figures,
    measure_training,
    median_update_ms,
    random_frames,
)
from dqnlab.config import Config, preset_names, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.lockstep import play_games
from dqnlab.run.state import TrainingState

FAMILY = ("nature", "double", "dueling", "prioritized", "c51", "rainbow", "qrdqn", "iqn")
FULL_REPLAY_SLOTS = 1_000_000


def parse_variants(text: str) -> list[str]:
    """`all` or a comma-separated list of shipped presets, checked."""
    names = list(FAMILY) if text == "all" else [n.strip() for n in text.split(",") if n.strip()]
    unknown = [name for name in names if name not in preset_names()]
    if unknown or not names:
        raise ConfigError(
            f"variants {text!r}: {', '.join(unknown) or 'nothing'} is not a shipped preset; "
            f"accepted: all, or a list of {', '.join(preset_names())}"
        )
    return names


def _sample(replay: ReplayMemory, config: Config) -> Any:
    return replay.sample(config.replay_start_steps)  # prioritized replay's beta at its start


def _run_minutes(
    preset: str, state: TrainingState, train_frames_per_second: float, steps: int
) -> dict[str, float]:
    """How long one whole run of the preset takes here: its total_steps at the training
    rate measured once learning runs (an upper bound: the replay-start steps do not
    update), and its final evaluation's rate (eval_epsilon, every core) per 10k agent
    steps, since how many steps its games last depends on what the agent learned."""
    config = state.config
    steps_per_second = train_frames_per_second / config.action_repeat_frames
    evaluation = play_games(
        state.agent, config, config.final_eval_episodes, config.seed,
        epsilon=config.eval_epsilon, max_episode_frames=config.final_eval_max_episode_frames,
        max_steps=steps,
    )  # fmt: skip
    eval_steps_per_second = evaluation.frames_per_second / config.action_repeat_frames
    return {
        f"{preset}_training_minutes_per_run": config.total_steps / steps_per_second / 60,
        f"{preset}_eval_frames_per_second": evaluation.frames_per_second,
        f"{preset}_eval_minutes_per_10k_steps": 10_000 / eval_steps_per_second / 60,
    }


def measure_variants(
    presets: list[str],
    env: str = "breakout",
    steps: int = 1000,
    replay_capacity: int = 100_000,
    device: torch.device | None = None,
    seed: int = 0,
    rounds: int = 2,
    update_repeats: int = 30,
) -> dict[str, Any]:
    """The figures of each preset in `presets` (see the module's docstring), as
    `{preset}_{figure}` keys beside the machine's."""
    device = device or torch.device("cpu")
    figures: dict[str, Any] = {
        "env": env,
        **machine_figures(device),
        "replay_capacity": replay_capacity,
        "steps": steps,
        "rounds": rounds,
        "variants": ",".join(presets),
    }
    states: dict[str, TrainingState] = {}
    for preset in presets:
        config = resolve_config(preset, env=env, seed=seed, replay_capacity=replay_capacity)
        states[preset] = TrainingState(config, device)
        figures.update(_update_figures(preset, states[preset], update_repeats))
    runs, splits = _training_rounds(states, steps, rounds)
    for preset, state in states.items():
        frames_per_second = float(np.mean(runs[preset]))
        figures[f"{preset}_train_frames_per_second"] = frames_per_second
        figures[f"{preset}_train_frames_per_second_runs"] = [round(f, 1) for f in runs[preset]]
        for part, fraction in splits[preset].items():
            figures[f"{preset}_train_split_{part}"] = fraction
        figures.update(_run_minutes(preset, state, frames_per_second, steps))
        state.close()
    figures.update(_ratios(figures, presets))
    full = measure_sampling(capacity=FULL_REPLAY_SLOTS, batch_size=32, repeats=2000, seed=seed)
    figures["prioritized_1m_sample_us"] = full["sample_us"]
    figures["prioritized_1m_update_us"] = full["update_us"]
    figures["prioritized_1m_sample_and_update_us"] = full["total_us"]
    return figures


def _update_figures(preset: str, state: TrainingState, update_repeats: int) -> dict[str, Any]:
    """The preset's replay filled; its minibatch draw (with the priority update that
    follows, where there is one) and its update, against its dense operations alone and a
    matrix multiply timed right after; the state then taken past the replay start and the
    epsilon anneal, as for most of a run, and warmed up."""
    config, replay, agent = state.config, state.replay, state.agent
    fill_replay(replay, random_frames(replay, np.random.default_rng(config.seed)), 4)

    def sample_and_tell() -> None:
        batch = _sample(replay, config)
        replay.sampler.tell(batch, np.abs(batch.rewards) + 0.5)  # uniform: nothing

    figures = {f"{preset}_sample_us": float(np.median(call_seconds(sample_and_tell, 1000)) * 1e6)}
    batch = _sample(replay, config)
    # Counted by PyTorch's own FLOP counter: the products of whatever the preset's parts
    # compute (IQN's fraction samples, C51's projection).
    flop = update_flops(agent, batch)
    update_ms = median_update_ms(agent, batch, update_repeats)
    dense = dense_figures(f"{preset}_", agent, batch, update_ms, update_repeats)
    matmul = measure_matmul(state.agent.device)
    figures[f"{preset}_update_ms"] = update_ms
    figures.update(dense)
    figures.update(update_flop_figures(f"{preset}_", flop, update_ms, matmul))
    figures[f"{preset}_matmul_gflop_per_s"] = matmul.median_gflop_per_s
    state.steps = config.replay_start_steps + config.epsilon_decay_steps
    for _ in range(100):
        state.advance()
    return figures


def _training_rounds(
    states: dict[str, TrainingState], steps: int, rounds: int
) -> tuple[dict[str, list[float]], dict[str, dict[str, float]]]:
    """Training frames/s of each preset in each of `rounds` alternating rounds, so that a
    change in the machine's load falls on every preset alike, and the shares of the parts
    of a step in its last round."""
    runs: dict[str, list[float]] = {preset: [] for preset in states}
    splits: dict[str, dict[str, float]] = {}
    for _ in range(rounds):
        for preset, state in states.items():
            frames_per_second, splits[preset] = measure_training(state, steps)
            runs[preset].append(frames_per_second)
    return runs, splits


def _ratios(figures: dict[str, Any], presets: list[str]) -> dict[str, float]:
    """Each preset's training frames/s against the nature preset's (when measured), and
    prioritized replay's against uniform's: the prioritized preset is the tuned Double DQN
    with prioritized replay."""
    ratios = {}
    base = figures.get("nature_train_frames_per_second")
    for preset in presets:
        if base:
            ratios[f"{preset}_train_ratio_vs_nature"] = (
                figures[f"{preset}_train_frames_per_second"] / base
            )
    if "prioritized" in presets and "double" in presets:
        ratios["prioritized_train_ratio_vs_double"] = (
            figures["prioritized_train_frames_per_second"]
            / figures["double_train_frames_per_second"]
        )
    return ratios
