"""Benchmark protocols: the settings a benchmark fixes, whatever the agent, so that its
scores can be set beside the published ones.

Atari 100k (Kaiser et al. 2019, "Model-Based Reinforcement Learning for Atari",
arXiv:1903.00374), as Dopamine's `dopamine/labs/atari_100k/configs/*.gin` and
`atari_100k_runner.py` run it (google/dopamine at 5873f54): 100,000 agent steps of the
deterministic ALE, then the last network's mean score over 100 episodes at ε 0.001
(docs/atari100k.md). Every atari100k preset (`der`, `drq_epsilon`) holds these values;
`dqnlab sweep --games atari100k` and `dqnlab report` say which a run departs from.
"""

from __future__ import annotations

from typing import Any

from dqnlab.config.settings import Config

ATARI100K_PROTOCOL: dict[str, Any] = {
    "sticky_action_probability": 0.0,  # "Atari 100K benchmark doesn't use sticky actions"
    "full_action_space": False,  # the game's minimal action set (Dopamine's default)
    "life_loss_terminal": True,  # AtariPreprocessing.terminal_on_life_loss = True
    "action_repeat_frames": 4,  # 100k agent steps = 400k frames
    "max_episode_frames": 108_000,  # Runner.max_steps_per_episode = 27,000 agent steps
    "total_steps": 100_000,  # Runner.num_iterations 10 x training_steps 10,000
    "final_eval_network": "last",  # the agent as it is after 100k steps
    "final_eval_episodes": 100,  # MaxEpisodeEvalRunner.num_eval_episodes
    "final_eval_max_episode_frames": 108_000,  # the same 27,000-step cap
    "eval_epsilon": 0.001,  # JaxDQNAgent.epsilon_eval
}


def atari100k_departures(config: Config) -> list[str]:
    """The settings in which `config` departs from the Atari 100k protocol, each as
    `name = value (the protocol: value)`; empty when it follows it."""
    return [
        f"{name} = {getattr(config, name)!r} (the protocol: {value!r})"
        for name, value in ATARI100K_PROTOCOL.items()
        if getattr(config, name) != value
    ]
