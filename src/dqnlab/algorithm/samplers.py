"""How the update's minibatches are drawn from the replay: the sampler part
(`replay_sampling = "uniform" | "prioritized" | "module:Class"`).

A sampler is bound to one replay memory (`bind`), hears of every slot the replay writes
(`written`), draws the minibatch of the update at an agent step (`sample`), is told what
the update made of it (`tell`: the loss part's per-transition priorities, None where the
loss gives none) and saves its own state with the replay's (`state_dict`). The training
loop calls `replay.sample(step)` and `replay.sampler.tell(batch, priorities)`, whatever the
sampler. A sampler whose `NEEDS_PRIORITIES` is true makes the run check, before it starts,
that the loss part gives priorities. A user's sampler is built as `Class(config)`.

`UniformSampler` is the Lua code's draw (uniform over the valid transitions, by
rejection). `PrioritizedSampler` is proportional prioritized replay (Schaul et al. 2016):
the sum tree's non-zero leaves are exactly the slots a transition can start from now
(`ReplayMemory.valid`), each write adjusting the few whose validity it changes
(`written`), so a draw never needs rejecting, unlike Dopamine's (the reference note's
§8.5); β, the importance weights' exponent, follows its schedule
(`losses.importance_exponent_at`) by the step the sampler is asked at.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.losses import importance_exponent_at
from dqnlab.algorithm.minibatch import Batch
from dqnlab.algorithm.prioritized import ProportionalPriorities, importance_weights
from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import load_object, load_part

# The replay memory a sampler is bound to (`replay.ReplayMemory`, which imports this
# module: named here by its role, not imported).
ReplayMemory = Any


class UniformSampler:
    """Uniform with replacement over the valid transitions (`ReplayMemory.sample_indices`)."""

    NEEDS_PRIORITIES = False

    def __init__(self, config: Config | None = None) -> None:
        self.replay: ReplayMemory | None = None

    def bind(self, replay: ReplayMemory) -> None:
        self.replay = _weak(replay)

    def written(self, slot: int) -> None:
        """Nothing to keep per slot."""

    def sample(self, step: int = 0) -> Batch:
        replay = _bound(self.replay)
        return replay.gather(replay.sample_indices(replay.batch_size))

    def tell(self, batch: Batch, priorities: torch.Tensor | np.ndarray | None) -> None:
        """Nothing to learn from the update."""

    def state_dict(self) -> dict[str, Any] | None:
        return None

    def load_state_dict(self, state: dict[str, Any] | None) -> None:
        """Nothing saved."""


class PrioritizedSampler:
    """Proportional prioritized replay: P(i) = p_i^α / Σ p^α, p_i = |error_i| + ε, new
    transitions at the largest priority, importance weights of exponent β(step)."""

    NEEDS_PRIORITIES = True

    def __init__(
        self,
        config: Config | None = None,
        *,
        priority_exponent: float | None = None,
        priority_epsilon: float | None = None,
        importance_exponent: Callable[[int], float] | float | None = None,
    ) -> None:
        """The run's α, ε and β schedule from `config`; the keywords, where given, instead
        (β a constant or a function of the step)."""
        settings = config or Config()
        self.exponent = (
            settings.priority_exponent if priority_exponent is None else priority_exponent
        )
        self.epsilon = settings.priority_epsilon if priority_epsilon is None else priority_epsilon
        if importance_exponent is None:
            self.beta: Callable[[int], float] = partial(importance_exponent_at, config=settings)
        elif callable(importance_exponent):
            self.beta = importance_exponent
        else:
            self.beta = partial(_constant_beta, beta=float(importance_exponent))
        self.replay: ReplayMemory | None = None
        self.priorities: ProportionalPriorities | None = None

    def bind(self, replay: ReplayMemory) -> None:
        """The sum tree over the replay's slots, and the buffers of a draw."""
        self.replay = _weak(replay)
        self.priorities = ProportionalPriorities(replay.capacity, self.exponent, self.epsilon)
        size = replay.batch_size
        self._uniforms = np.zeros(size)
        self._sampled = np.zeros(size, dtype=np.int64)
        self._probabilities = np.zeros(size)
        replay.minibatch.weights = np.ones(size, dtype=np.float32)
        # The slots whose validity writing slot 0 can change (`written`).
        self._refresh_offsets = np.arange(-replay.n_step, replay.history_length, dtype=np.int64)
        # Where the rings were at the last draw: what `tell` leaves alone.
        self._sampled_mark = replay.streams.mark()

    def written(self, slot: int) -> None:
        """Keep the non-zero leaves exactly the valid slots after writing `slot`.

        A write can change the validity of these slots alone: the one written (now the
        newest: no next state yet), the n_step before it (a window may now end in it: valid
        from now on, at the largest priority, Schaul et al. 2016, Algorithm 1) and, once
        the ring is full, the history_length - 1 after it (the oldest: their histories now
        reach back into the slot just overwritten). A few leaves, set in one tree update.
        """
        replay, priorities = _bound(self.replay), _bound(self.priorities)
        slots = replay.streams.wrap(np.array([slot]), self._refresh_offsets)[0]
        leaves = priorities.tree.leaves[slots]
        wanted = np.where(leaves > 0.0, leaves, priorities.new_leaf)
        wanted[~replay.valid(slots)] = 0.0
        changed = wanted != leaves
        if changed.any():
            priorities.tree.set(slots[changed], wanted[changed])

    def sample(self, step: int = 0) -> Batch:
        """A stratified draw of the batch from the tree, with importance weights of
        exponent β(step) in `weights`."""
        replay, priorities = _bound(self.replay), _bound(self.priorities)
        if not priorities.tree.total > 0.0:
            raise RuntimeError("the replay memory holds no complete transition yet")
        replay.rng.random(out=self._uniforms)
        priorities.sample(self._uniforms, self._sampled, self._probabilities)
        batch = replay.gather(self._sampled)
        assert batch.weights is not None  # `bind` gave the batch its weights
        # N = the slots stored; it cancels in the batch-max normalisation.
        importance_weights(self._probabilities, replay.size, self.beta(step), batch.weights)
        self._sampled_mark = replay.streams.mark()
        return batch

    def tell(self, batch: Batch, priorities: torch.Tensor | np.ndarray | None) -> None:
        """The errors (>= 0: |TD error|, or a per-transition loss, as the loss part gives)
        of the transitions of the latest `sample`: their priorities become (error + ε)^α
        (Schaul et al. 2016, Algorithm 1 line 12). Slots written since that sample are left
        alone (their priority would belong to another transition: ray-project/ray#6534),
        and so are slots that stopped being valid; where an index repeats, its last error
        counts."""
        if priorities is None or batch.indices is None:
            raise ValueError("prioritized replay needs the update's priorities and indices")
        self.update(batch.indices, priorities)

    def update(self, indices: np.ndarray, errors: np.ndarray | torch.Tensor) -> None:
        """`tell`'s work, for given slots and errors."""
        replay, priorities = _bound(self.replay), _bound(self.priorities)
        if isinstance(errors, torch.Tensor):
            errors = errors.detach().to("cpu", torch.float64).numpy()
        errors = np.asarray(errors, dtype=np.float64).reshape(-1)
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        if errors.shape != indices.shape:
            raise ValueError(f"{len(errors)} errors for {len(indices)} indices")
        keep = priorities.tree.leaves[indices] > 0.0
        # The slots written since the draw hold other transitions now.
        positions, writes = self._sampled_mark
        streams = replay.streams
        written = np.minimum(np.subtract(streams.writes, writes), streams.segment)
        if written.any():
            stream, local = streams.locate(indices)
            since = (local - np.asarray(positions)[stream]) % streams.segment
            keep &= since >= written[stream]
        priorities.update(indices[keep], errors[keep])

    def state_dict(self) -> dict[str, Any] | None:
        """The tree and the largest priority (8 bytes a slot), so a resumed run draws the
        same minibatches."""
        return _bound(self.priorities).state_dict()

    def load_state_dict(self, state: dict[str, Any] | None) -> None:
        """The saved priorities; without them (a state saved under uniform sampling), every
        valid slot at the largest priority, the others 0."""
        replay, priorities = _bound(self.replay), _bound(self.priorities)
        if state is not None:
            priorities.load_state_dict(state)
        else:
            valid = replay.valid(np.arange(replay.capacity))
            priorities.tree.load(np.where(valid, priorities.new_leaf, 0.0))
        self._sampled_mark = replay.streams.mark()


# What a sampler part must have (docs/own-variant.md, A sampler).
SAMPLER_METHODS = ("bind", "written", "sample", "tell", "state_dict", "load_state_dict")


def build_sampler(config: Config) -> Any:
    """The sampler `replay_sampling` names, built with the run's settings."""
    if config.replay_sampling == "uniform":
        return UniformSampler(config)
    if config.replay_sampling == "prioritized":
        return PrioritizedSampler(config)
    sampler = load_part("replay_sampling", config.replay_sampling, config)
    missing = [name for name in SAMPLER_METHODS if not callable(getattr(sampler, name, None))]
    if missing:
        raise ConfigError(
            f"replay_sampling = {config.replay_sampling!r} has no {', '.join(missing)}: a "
            f"sampler needs {', '.join(SAMPLER_METHODS)} (docs/own-variant.md, A sampler)"
        )
    return sampler


def needs_priorities(config: Config) -> bool:
    """Whether the run's sampler asks the loss part for priorities."""
    if config.replay_sampling in ("uniform", "prioritized"):
        return config.replay_sampling == "prioritized"
    sampler = load_object("replay_sampling", config.replay_sampling)
    return bool(getattr(sampler, "NEEDS_PRIORITIES", False))


def _constant_beta(step: int, beta: float) -> float:
    return beta


def _weak(replay: ReplayMemory) -> ReplayMemory:
    """The replay as a weak reference: it holds its sampler, and a strong reference back
    would make the pair a cycle, kept (a 7 GB replay with it) until the garbage collector's
    next pass instead of freed when the run drops it."""
    return weakref.proxy(replay)


def _bound(value: Any) -> Any:
    if value is None:
        raise RuntimeError("the sampler is not bound to a replay memory (ReplayMemory binds it)")
    return value
