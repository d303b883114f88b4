"""The held-out transitions of Nature's Figure 2: the average predicted action value.

Nature's Figure 2 plots, beside the scores, the average of max_a Q over a fixed set of
states: it rises smoothly where the scores are noisy, and shows early that learning
works. DeepMind's Lua code (NeuralQLearner.lua) draws `valid_size` = 500 transitions
from the replay memory once, when `numSteps == learn_start + 1`
(`sample_validation_data`), and at every evaluation (train_agent.lua) logs
`compute_validation_statistics`: from its `getQUpdate`,

    v_avg     = mean over the set of max_a Q_target(s', a)
    tderr_avg = mean over the set of |clip(r + discount (1 - terminal) max_a Q_target(s', a)
                                          - Q_online(s, a), -clip_delta, clip_delta)|

Q_target is the target network (the Lua code's `target_q_net` with target_q set), and
s' the transition's next state; both figures are computed here as the Lua code does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.replay import ReplayMemory


@dataclass(frozen=True)
class HeldOutStatistics:
    """The two figures DeepMind's code logs at each evaluation (v_avg, tderr_avg)."""

    max_q: float  # mean over the set of max_a Q_target(s', a)
    td_error: float  # mean |TD error|, clipped as in the update


@dataclass
class HeldOutSet:
    """Transitions drawn once from the replay memory and kept, frames included, so that
    every evaluation (and a resumed run) measures the same states.

    `windows` holds each transition's history + 1 frames: s is the first `history`, s'
    the last `history`, as the replay's minibatches hold them."""

    windows: torch.Tensor  # (size, history + 1, *frame_shape), the replay's dtype, CPU
    actions: torch.Tensor  # (size,) int64
    rewards: torch.Tensor  # (size,) float32, clipped as stored
    terminals: torch.Tensor  # (size,) float32, 1.0 where s' is terminal

    @classmethod
    def draw(cls, replay: ReplayMemory, size: int, rng: np.random.Generator) -> HeldOutSet | None:
        """`size` transitions uniform with replacement (as the replay's minibatches), with
        `rng` rather than the replay's own generator, so that drawing the set changes no
        minibatch of the run. None while the replay holds no complete transition.

        One-step transitions whatever the replay's n_step (`gather_windows`): the figure
        is the Lua code's, r + γ max_a Q_target(s', a) of a single step."""
        if not replay.has_transition():
            return None
        indices = replay.sample_indices(size, rng)
        windows, actions, rewards, terminals = [], [], [], []
        batch_size = replay.batch_size
        for start in range(0, size, batch_size):
            part = indices[start : start + batch_size]
            padded = np.resize(part, batch_size)  # gather takes whole minibatches
            batch = replay.gather_windows(padded)
            count = len(part)
            assert batch.window is not None
            windows.append(torch.as_tensor(batch.window[:count]).cpu().clone())
            actions.append(torch.from_numpy(batch.actions[:count].copy()))
            rewards.append(torch.from_numpy(batch.rewards[:count].copy()))
            terminals.append(torch.from_numpy(batch.terminals[:count].copy()))
        return cls(torch.cat(windows), torch.cat(actions), torch.cat(rewards), torch.cat(terminals))

    def __len__(self) -> int:
        return len(self.actions)

    def statistics(
        self,
        online: torch.nn.Module,
        target: torch.nn.Module,
        discount: float,
        td_error_clip: float,
        device: torch.device,
        batch_size: int = 250,
    ) -> HeldOutStatistics:
        """Both figures, with the networks in eval mode, `batch_size` transitions at a
        time (a bounded amount of device memory)."""
        history = self.windows.shape[1] - 1
        max_q_sum, td_error_sum = 0.0, 0.0
        online.eval()
        target.eval()
        with torch.inference_mode():
            for start in range(0, len(self), batch_size):
                stop = start + batch_size
                windows = self.windows[start:stop].to(device)
                observations, next_observations = windows[:, :history], windows[:, 1:]
                actions = self.actions[start:stop].to(device)
                next_max_q = target(next_observations).float().max(dim=1).values
                q_taken = online(observations).float().gather(1, actions[:, None]).squeeze(1)
                rewards = self.rewards[start:stop].to(device)
                not_terminal = 1.0 - self.terminals[start:stop].to(device)
                td_error = rewards + discount * not_terminal * next_max_q - q_taken
                if td_error_clip > 0:
                    td_error = td_error.clamp(-td_error_clip, td_error_clip)
                max_q_sum += float(next_max_q.sum())
                td_error_sum += float(td_error.abs().sum())
        return HeldOutStatistics(max_q_sum / len(self), td_error_sum / len(self))

    def state_dict(self) -> dict[str, Any]:
        return {
            "windows": self.windows,
            "actions": self.actions,
            "rewards": self.rewards,
            "terminals": self.terminals,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> HeldOutSet:
        return cls(state["windows"], state["actions"], state["rewards"], state["terminals"])
