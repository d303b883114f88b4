"""n-step returns, computed when a minibatch is drawn from the single steps the replay
stores (as Dopamine's circular_replay_buffer.py `sample_transition_batch` does): no
second buffer, and n is a setting of the draw, not of what was stored.

Rainbow (Hessel et al. 2018, section "Multi-step learning"): R_t^(n) = Σ_{k<n} γ_t^(k)
r_{t+k+1} with γ_t^(k) the product of the per-step discounts, γ except 0 at termination,
and the target bootstraps from S_{t+n} with γ_t^(n). In this replay's slots (slot t holds
o_t, a_t, r_t and whether o_{t+1} is terminal; an episode's last observation has a slot of
its own, `is_last`) a window of m <= n steps starting at slot t is cut short:

- at a terminal step t + k (life losses included when `life_loss_terminal` stores them as
  terminal): m = k + 1, and the target does not bootstrap;
- at a step t + k whose next observation is an episode's last without being terminal (a
  time-limit truncation): m = k + 1, and the target bootstraps from that observation with
  γ^m, as dqn_zoo's `NStepTransitionAccumulator` and SB3's `NStepReplayBuffer` do (the
  reference note's §4 and §8.3; Dopamine drops such windows instead).

So the target is Σ_{k<m} γ^k r_{t+k} + γ^m (1 - terminal) max_a Q(o_{t+m}, a).
"""

from __future__ import annotations

import numpy as np


def ring_slots(starts: np.ndarray, offsets: np.ndarray, segment: int) -> np.ndarray:
    """Slots `offsets` after each of `starts`, wrapped round the start's own segment of
    `segment` slots (the replay's streams, `streams.py`; one segment: the whole ring)."""
    bases = starts - starts % segment
    return bases[:, None] + ((starts - bases)[:, None] + offsets) % segment


def window_steps(
    terminals: np.ndarray,
    is_last: np.ndarray,
    starts: np.ndarray,
    n_step: int,
    segment: int | None = None,
) -> np.ndarray:
    """m for the window starting at each slot of `starts`: the steps t..t+m-1 it sums, its
    next state being slot t + m. Reads the flags of slots t..t+n, stored or not: a window
    whose end is not stored yet is the caller's to reject (`ReplayMemory._valid`).
    `segment`: the slots of a stream's ring (default: all of them, one ring)."""
    segment = segment or len(terminals)
    slots = ring_slots(starts, np.arange(n_step + 1), segment)
    ends = terminals[slots[:, :-1]]
    ends |= is_last[slots[:, 1:]]
    ends[:, -1] = True  # after n steps at the latest
    return ends.argmax(axis=1) + 1


def discount_powers(discount: float, n_step: int) -> np.ndarray:
    """γ^0 .. γ^n, float64."""
    return np.power(float(discount), np.arange(n_step + 1, dtype=np.float64))


def n_step_targets(
    rewards: np.ndarray,
    terminals: np.ndarray,
    starts: np.ndarray,
    steps: np.ndarray,
    powers: np.ndarray,
    out_returns: np.ndarray,
    out_terminals: np.ndarray,
    out_discounts: np.ndarray,
    segment: int | None = None,
) -> None:
    """Into the `out_` arrays (float32): Σ_{k<m} γ^k r_{t+k} of the rewards as stored
    (clipped), summed in float64; 1.0 where the window's last step is terminal; γ^m.
    `powers`: `discount_powers(γ, n)`; `steps`: m of each window (`window_steps`)."""
    segment = segment or len(rewards)
    n_step = len(powers) - 1
    offsets = np.arange(n_step)
    slots = ring_slots(starts, offsets, segment)
    summed = rewards[slots] * powers[:n_step]
    summed[offsets >= steps[:, None]] = 0.0
    out_returns[...] = summed.sum(axis=1)
    bases = starts - starts % segment
    out_terminals[...] = terminals[bases + (starts - bases + steps - 1) % segment]
    out_discounts[...] = powers[steps]
