"""Small networks, where the per-update overhead is all there is: `dqnlab bench small`
(issue 32).

The update alone of each (`median_update_ms`, one minibatch of a replay filled with random
observations), as updates per second and against its dense operations alone (`dense.py`):
`mlp`, the `classic` preset's 256-256 MLP on CartPole-v1's 4 floats; `small_cnn`, MinAtar's
network (on the `classic` preset) on a packed 10x10x4 bool image, MinAtar Breakout's (no
MinAtar needed); `der_cnn`, the `der` preset's network and head on 4 stacked 84x84 frames.

Then the `classic` preset's training steps/s on CartPole-v1 and, with `peers`,
Stable-Baselines3's `DQN("MlpPolicy", "CartPole-v1")` with the same settings under SB3's
names (`sb3_dqn_kwargs`), in alternating rounds, in this process on the same device and
threads. Each is timed over `steps` agent steps once learning runs, at the final ε as for
most of a run: dqnlab's state plays its replay start, then skips its anneal (as
`throughput.py` does); SB3, a fresh model each round, anneals over its learning starts,
where it acts at random whatever ε is. What SB3 cannot be told: it anneals ε from step 0,
dqnlab from the end of the replay start (both are final in the timed steps); it always
clips the gradient's norm, so classic's no clip is `max_grad_norm = inf` (the norm is still
computed); `SB3_FIXED` lists the parts it has built in, checked against the config.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.algorithm.samplers import build_sampler
from dqnlab.bench.dense import dense_figures
from dqnlab.bench.measure import fill_replay, machine_figures, measure_training, median_update_ms
from dqnlab.config import Config, resolve_config
from dqnlab.envs.spaces import ObservationLayout, observation_layout
from dqnlab.errors import ConfigError
from dqnlab.run.denormals import denormals_kept
from dqnlab.run.state import TrainingState

if TYPE_CHECKING:
    from stable_baselines3 import DQN

ENV = "CartPole-v1"
REPLAY_SLOTS = 5_000  # enough for DER's 20-step windows; the update's time does not depend on it
WARMUP_STEPS = 100  # after the jump past the ε anneal, not timed
# SB3's DQN kwarg -> the dqnlab setting it takes (the rest: `sb3_dqn_kwargs`).
SB3_NAMES = {
    "learning_rate": "learning_rate",
    "buffer_size": "replay_capacity",
    "learning_starts": "replay_start_steps",
    "batch_size": "batch_size",
    "gamma": "discount",
    "train_freq": "update_period_steps",  # agent steps, as SB3's (n, "step")
    "target_update_interval": "target_update_steps",  # agent steps in both
    "exploration_initial_eps": "epsilon_start",
    "exploration_final_eps": "epsilon_end",
}
# What SB3's DQN does and cannot be told otherwise (SB3 2.9, dqn.py and policies.py): one
# observation, no reward clip, 1-step max targets, a mean Huber loss of delta 1, Adam,
# uniform replay, one environment.
SB3_FIXED: dict[str, Any] = {
    "history_length": 1, "reward_clip": 0.0, "n_step": 1, "target": "max",
    "distributional": "none", "dueling": False, "noisy": False, "td_error_clip": 1.0,
    "loss_reduction": "mean", "optimizer": "adam", "replay_sampling": "uniform",
    "policy": "epsilon_greedy", "augmentation": "none", "num_envs": 1,
}  # fmt: skip


@dataclass(frozen=True)
class SmallNetwork:
    """One network measured: its preset (with `network` over it where given), the
    observation it reads and its number of actions."""

    preset: str
    env: str
    observation: gym.spaces.Box
    actions: int
    network: str | None = None


def small_networks() -> dict[str, SmallNetwork]:
    """The networks measured, by the prefix of their figures (fresh spaces: seeding one
    changes it)."""
    # MinAtar Breakout-v1's observation; gymnasium's stubs allow float Box dtypes only.
    minatar = gym.spaces.Box(0, 1, (10, 10, 4), np.bool_)  # type: ignore[arg-type]
    return {
        "mlp": SmallNetwork("classic", ENV, gym.spaces.Box(-1.0, 1.0, (4,), np.float32), 2),
        "small_cnn": SmallNetwork("classic", ENV, minatar, 6, "small_cnn"),  # its full action set
        "der_cnn": SmallNetwork("der", "breakout", gym.spaces.Box(0, 255, (84, 84), np.uint8), 4),
    }


def measure_small_networks(
    steps: int = 5000,
    rounds: int = 2,
    device: torch.device | None = None,
    peers: bool = False,
    seed: int = 0,
    update_repeats: int = 100,
) -> dict[str, Any]:
    """Every figure of the module's docstring, as `{network}_{figure}` and
    `classic_` / `sb3_` keys beside the machine's."""
    if steps < 1 or rounds < 1:
        raise ConfigError(f"steps and rounds must be at least 1: {steps}, {rounds}")
    device = device or torch.device("cpu")
    figures: dict[str, Any] = {"env": ENV, **machine_figures(device), "steps": steps}
    figures["rounds"] = rounds
    for name, network in small_networks().items():
        figures.update(network_update_figures(name, network, device, update_repeats, seed))
    figures.update(training_against_sb3(steps, rounds, device, peers, seed))
    return figures


def network_update_figures(
    name: str, network: SmallNetwork, device: torch.device, repeats: int, seed: int
) -> dict[str, Any]:
    """The network's update alone on one minibatch of a filled replay: its median time,
    updates per second, and its dense operations alone."""
    config = resolve_config(network.preset, env=network.env, seed=seed, network=network.network)
    layout = observation_layout(network.observation)
    input_shape = (config.history_length, *layout.frame_shape)
    actions = [f"action_{index}" for index in range(network.actions)]
    agent = agent_for_input(config, input_shape, layout.frame_dtype, actions, device, seed, layout)
    replay = ReplayMemory(
        REPLAY_SLOTS, layout.frame_shape, layout.frame_dtype, config.history_length,
        config.batch_size, seed, n_step=config.n_step, discount=config.discount,
        sampler=build_sampler(config),
    )  # fmt: skip
    network.observation.seed(seed)
    fill_replay(replay, _observations(layout, network.observation), 2)
    batch = replay.sample(config.replay_start_steps)  # prioritized replay's β at its start
    update_ms = median_update_ms(agent, batch, repeats)
    shape = "x".join(map(str, network.observation.shape))
    return {
        f"{name}_preset": network.preset,
        f"{name}_input": f"{input_shape[0]} x {shape} {network.observation.dtype}",  # history x
        f"{name}_batch_size": config.batch_size,
        f"{name}_parameters": sum(p.numel() for p in agent.online.parameters()),
        f"{name}_update_ms": update_ms,
        f"{name}_updates_per_second": 1e3 / update_ms,
        **dense_figures(f"{name}_", agent, batch, update_ms, repeats),
    }


def _observations(layout: ObservationLayout, space: gym.spaces.Box) -> np.ndarray:
    """A pool of 64 random observations of `space`, stored as a run stores them."""
    pool = np.zeros((64, *layout.frame_shape), dtype=layout.frame_dtype)
    for frame in pool:
        layout.pack(space.sample(), frame)
    return pool


def training_against_sb3(
    steps: int, rounds: int, device: torch.device, peers: bool, seed: int
) -> dict[str, Any]:
    """The classic preset's training steps/s on CartPole-v1 in each of `rounds` rounds, each
    followed by SB3's with the same settings (with `peers`), and dqnlab's ratio to it."""
    state = _classic_past_the_anneal(device, seed)
    classic_runs, sb3_runs = [], []
    try:
        for _ in range(rounds):
            classic_runs.append(measure_training(state, steps))  # a frame is a step here
            if peers:
                with denormals_kept():  # SB3 as its users run it
                    sb3_runs.append(run_sb3_classic(state.config, steps, device))
    finally:
        state.close()
    classic = float(np.mean([steps_per_second for steps_per_second, _ in classic_runs]))
    figures: dict[str, Any] = {
        "classic_train_steps_per_second": classic,
        "classic_train_steps_per_second_runs": [round(run, 1) for run, _ in classic_runs],
        **{f"classic_train_split_{part}": share for part, share in classic_runs[-1][1].items()},
    }
    if sb3_runs:
        sb3 = [run.pop("sb3_train_steps_per_second") for run in sb3_runs]
        figures["sb3_train_steps_per_second"] = float(np.mean(sb3))
        figures["sb3_train_steps_per_second_runs"] = [round(run, 1) for run in sb3]
        figures["classic_over_sb3"] = classic / figures["sb3_train_steps_per_second"]
        figures.update(sb3_runs[-1])  # its version and settings
    return figures


def _classic_past_the_anneal(device: torch.device, seed: int) -> TrainingState:
    """The classic preset on CartPole-v1 with its replay start played (random actions,
    real transitions), then taken past the ε anneal and warmed up."""
    config = resolve_config("classic", env=ENV, seed=seed)
    state = TrainingState(config, device)
    while state.steps < config.replay_start_steps:
        state.advance()
    state.steps = config.replay_start_steps + config.epsilon_decay_steps
    for _ in range(WARMUP_STEPS):
        state.advance()
    return state


def sb3_dqn_kwargs(
    config: Config, total_steps: int, epsilon_decay_steps: int | None = None
) -> dict[str, Any]:
    """The config's settings under the names of SB3's DQN, for a `learn()` of
    `total_steps` (SB3 anneals ε over a fraction of it) with ε annealed over
    `epsilon_decay_steps` (default the config's); a setting SB3 cannot take is refused."""
    differ = {k: getattr(config, k) for k, v in SB3_FIXED.items() if getattr(config, k) != v}
    if config.network not in ("auto", "mlp") or differ:
        raise ValueError(f"SB3's DQN cannot run network={config.network!r} or {differ}")
    decay_steps = config.epsilon_decay_steps if epsilon_decay_steps is None else epsilon_decay_steps
    return {
        **{sb3: getattr(config, setting) for sb3, setting in SB3_NAMES.items()},
        "gradient_steps": 1,  # one update every update_period_steps
        "exploration_fraction": decay_steps / total_steps,
        "max_grad_norm": config.max_gradient_norm or math.inf,  # 0: no clip
        "policy_kwargs": {
            "net_arch": list(config.mlp_hidden_sizes),  # ReLU, as dqnlab's MLP
            "optimizer_class": torch.optim.Adam,
            "optimizer_kwargs": {"eps": config.adam_epsilon},
        },
    }


def make_sb3_classic(
    config: Config, total_steps: int, device: torch.device, epsilon_decay_steps: int | None = None
) -> DQN:
    """SB3's `DQN("MlpPolicy", env)`, as a user makes it, on the config's Gymnasium
    environment and seed, with its settings (`sb3_dqn_kwargs`)."""
    from stable_baselines3 import DQN

    kwargs = sb3_dqn_kwargs(config, total_steps, epsilon_decay_steps)
    return DQN("MlpPolicy", config.env, seed=config.seed, device=str(device), verbose=0, **kwargs)


def run_sb3_classic(config: Config, steps: int, device: torch.device) -> dict[str, Any]:
    """A fresh SB3 model trained for its learning starts and `steps` more; its steps/s over
    the last `steps` (ε final: annealed over the learning starts), its settings read back."""
    import stable_baselines3
    from stable_baselines3.common.callbacks import BaseCallback

    class LearningClock(BaseCallback):  # notes the time and step when learning starts
        start, steps = 0.0, -1

        def _on_step(self) -> bool:
            if self.steps < 0 and self.num_timesteps >= config.replay_start_steps:
                self.steps, self.start = self.num_timesteps, time.perf_counter()
            return True

    total_steps = config.replay_start_steps + steps
    model = make_sb3_classic(config, total_steps, device, config.replay_start_steps)
    clock = LearningClock()
    try:
        model.learn(total_timesteps=total_steps, callback=clock)  # ends with its last update
        seconds = time.perf_counter() - clock.start
    finally:
        model.env.close()  # type: ignore[union-attr]
    return {
        "sb3_version": stable_baselines3.__version__,
        "sb3_train_steps_per_second": (model.num_timesteps - clock.steps) / seconds,
        "sb3_settings": sb3_settings(model, total_steps),
        "sb3_settings_from": SB3_NAMES,  # the rest: sb3_dqn_kwargs
    }


def sb3_settings(model: DQN, total_steps: int) -> dict[str, Any]:
    """The settings SB3 ran with, read back from the model, under its names."""
    train_freq = model.train_freq  # a TrainFreq once the model is set up
    optimizer = model.policy.optimizer
    return {
        "net_arch": list(model.policy.net_arch),
        **{name: getattr(model, name) for name in SB3_NAMES if name != "train_freq"},
        "train_freq": train_freq.frequency,  # type: ignore[union-attr]
        "train_freq_unit": train_freq.unit.value,  # type: ignore[union-attr]
        "gradient_steps": model.gradient_steps,
        "tau": model.tau,
        "exploration_decay_steps": round(model.exploration_fraction * total_steps),
        "optimizer": type(optimizer).__name__,
        "optimizer_eps": optimizer.defaults["eps"],
        "loss": "smooth_l1_loss (Huber, delta 1, mean over the batch)",  # SB3 DQN.train
        "max_grad_norm": model.max_grad_norm if math.isfinite(model.max_grad_norm) else "inf",
        "updates": model._n_updates,
    }
