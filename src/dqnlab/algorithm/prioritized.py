"""Proportional prioritized replay (Schaul et al. 2016): priorities of the replay's slots
in a sum tree, sampled in proportion to them.

Section 3.3 of the paper: the priority of transition i is p_i = |δ_i| + ε and it is drawn
with probability P(i) = p_i^α / Σ_k p_k^α; section 3.4: its update is weighted by
w_i = (N · P(i))^-β, divided by the largest weight so that weights only scale updates
down. A new transition enters at the largest priority seen so far (Algorithm 1, line 6;
p_1 = 1), so that it is replayed at least once soon. The minibatch is drawn stratified: the
total mass is cut into `batch_size` segments of equal mass and one transition is drawn in
each (Appendix B.2.1), which lowers the variance of the minibatch's make-up.

The tree is float64 (dqn_zoo and Dopamine; float32 trees drew zero-priority items,
instadeepai/flashbax#52), each parent is recomputed from its children instead of being
moved by deltas (Dopamine's sum_tree.py notes the "tolerable numerical inaccuracies" of
deltas), and the descent never enters a zero-mass child, rounding or not.

Which slots hold a non-zero priority (the valid transitions) is the replay memory's
business (`ReplayMemory`); this module knows slots and numbers only.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np
import torch

# Children per node. Wider nodes mean fewer levels, and so fewer NumPy calls per descent
# and per update, each of which costs about a microsecond however few its elements: a 1M
# tree has 4 levels below its root at 32, 20 at 2 (`measure_sampling` compares them).
FANOUT = 32
# Smallest leaf of a valid slot: with priority_epsilon = 0 a zero error would otherwise give
# a zero leaf, which `ReplayMemory` reserves for slots that cannot be sampled.
SMALLEST_LEAF = float(np.finfo(np.float64).tiny)


class SumTree:
    """Non-negative float64 values of `capacity` leaves and the sums of every subtree.

    Level 0 is the root; each node of a level has `fanout` children on the next level, the
    last level being the leaves (each level padded with zero nodes to a multiple of
    `fanout`). `find` descends one level at a time for a whole batch of targets at once.
    """

    def __init__(self, capacity: int, fanout: int = FANOUT) -> None:
        if capacity < 1 or fanout < 2:
            raise ValueError(
                f"a sum tree needs capacity >= 1 and fanout >= 2, not {capacity}, {fanout}"
            )
        self.capacity = capacity
        self.fanout = fanout
        counts = [capacity]  # nodes of each level, leaves first
        while counts[-1] > 1:
            counts.append(-(-counts[-1] // fanout))
        counts.reverse()
        # levels[l]: level l padded to whole rows of `fanout` (the root alone is not).
        self._levels = [np.zeros(1)] + [
            np.zeros(-(-count // fanout) * fanout) for count in counts[1:]
        ]
        # rows[l][j]: the children of node j of level l, a view into level l + 1.
        self._rows = [level.reshape(-1, fanout) for level in self._levels[1:]]
        self.leaves = self._levels[-1][:capacity]  # a view: read it, change it with `set`

    @property
    def depth(self) -> int:
        """Levels below the root."""
        return len(self._rows)

    @property
    def total(self) -> float:
        return float(self._levels[0][0])

    def set(self, indices: np.ndarray, values: np.ndarray) -> None:
        """leaves[indices] = values; where an index repeats, its last value is the one kept
        (NumPy leaves the order of a repeated fancy assignment undefined)."""
        indices = np.asarray(indices, dtype=np.int64)
        values = np.asarray(values, dtype=np.float64)
        _check_values(values)
        if len(indices) > 1 and len(set(indices.tolist())) < len(indices):
            unique, last = np.unique(indices[::-1], return_index=True)
            indices, values = unique, values[::-1][last]
        self._levels[-1][indices] = values
        for level in range(self.depth - 1, -1, -1):
            indices = indices // self.fanout
            self._levels[level][indices] = _sums(self._rows[level][indices])

    def load(self, leaves: np.ndarray) -> None:
        """Replace every leaf and recompute every sum (the sums `set` gives, bit for bit)."""
        leaves = np.asarray(leaves, dtype=np.float64)
        if leaves.shape != (self.capacity,):
            raise ValueError(f"{leaves.shape[0]} leaves for a tree of {self.capacity}")
        _check_values(leaves)
        self.leaves[...] = leaves
        for level in range(self.depth - 1, -1, -1):
            sums = _sums(self._rows[level])
            self._levels[level][: len(sums)] = sums

    def find(self, targets: np.ndarray) -> np.ndarray:
        """For each target in [0, total): the leaf i with leaves[:i].sum() <= target <
        leaves[:i + 1].sum(), so that a uniform target picks leaf i with probability
        leaves[i] / total. Never a zero leaf: a child is entered only where the running
        sum of its siblings passes the target, which a zero child cannot do (x + 0 == x),
        and a target that rounding carries past a node's last child is given to the last
        child with non-zero mass."""
        if not self.total > 0.0:
            raise ValueError("the sum tree is empty (total 0): nothing to draw")
        targets = np.array(targets, dtype=np.float64)  # a copy: reduced level by level
        count = len(targets)
        nodes = np.zeros(count, dtype=np.int64)
        rows = np.arange(count)
        fanout = self.fanout
        # prefix[:, c]: the mass of children 0..c-1 of each node (column 0 is 0).
        prefix = np.zeros((count, fanout + 1))
        for children_of in self._rows:
            children = children_of[nodes]
            np.add.accumulate(children, axis=1, out=prefix[:, 1:])
            chosen = np.count_nonzero(prefix[:, 1:] <= targets[:, None], axis=1)
            past = chosen == fanout
            if past.any():  # rounding: the last child with mass (there is one)
                last = fanout - 1 - np.argmax(children[past, ::-1] > 0.0, axis=1)
                chosen[past] = last
            targets -= prefix[rows, chosen]
            nodes = nodes * fanout + chosen
        return nodes


def _sums(rows: np.ndarray) -> np.ndarray:
    """The value of each node: its children (a row) summed left to right, the order in
    which `find` accumulates them, so that a node's children add up to it exactly."""
    return np.add.accumulate(rows, axis=1)[:, -1]


def _check_values(values: np.ndarray) -> None:
    if not ((values >= 0.0).all() and np.isfinite(values).all()):
        raise ValueError("sum tree values must be finite and non-negative")


def importance_weights(
    probabilities: np.ndarray, count: int, exponent: float, out: np.ndarray | None = None
) -> np.ndarray:
    """w_i = (count · P(i))^-exponent / max_j w_j over the batch (Schaul et al. 2016,
    Algorithm 1 line 10), float32.

    The paper's max_i w_i may be read as over the batch or over the whole memory (the
    reference note's §8.2); dqn_zoo (`importance_sampling_weights`), Dopamine's Rainbow,
    CleanRL and Kaixhin/Rainbow all take the batch maximum, and so does this. With it,
    `count` (N, the transitions stored) cancels out: w_i = (P(i) / min_j P(j))^-exponent.
    """
    weights = np.power(count * np.asarray(probabilities, dtype=np.float64), -exponent)
    weights /= weights.max()
    if out is None:
        return weights.astype(np.float32)
    out[...] = weights
    return out


class ProportionalPriorities:
    """The leaves (|error| + ε)^α of the replay's slots, the running maximum priority and
    the stratified draw (Schaul et al. 2016, proportional variant).

    `max_priority` is a raw priority |error| + ε (before the exponent), as dqn_zoo and
    CleanRL keep it; it starts at 1 (Algorithm 1, p_1 = 1), and new transitions enter at
    `new_leaf` = max_priority^α. (Dopamine JAX keeps it after the exponent and applies the
    exponent again on insert: the reference note's §8.2.)
    """

    def __init__(
        self, capacity: int, exponent: float, epsilon: float, fanout: int = FANOUT
    ) -> None:
        if exponent < 0.0 or epsilon < 0.0:
            raise ValueError(
                f"priority exponent {exponent} and epsilon {epsilon} must be zero or more"
            )
        self.tree = SumTree(capacity, fanout)
        self.exponent = exponent
        self.epsilon = epsilon
        self.max_priority = 1.0

    @property
    def new_leaf(self) -> float:
        """The leaf of a transition not replayed yet: the largest priority seen."""
        return max(self.max_priority**self.exponent, SMALLEST_LEAF)

    def leaf_values(self, errors: np.ndarray) -> np.ndarray:
        """(|error| + ε)^α, at least `SMALLEST_LEAF` (a valid slot's leaf is never 0)."""
        return np.maximum(np.power(errors + self.epsilon, self.exponent), SMALLEST_LEAF)

    def update(self, slots: np.ndarray, errors: np.ndarray) -> None:
        """Set the priorities of `slots` from their errors (>= 0) and raise the maximum."""
        errors = np.asarray(errors, dtype=np.float64)
        if len(errors) == 0:
            return
        if not np.all(np.isfinite(errors) & (errors >= 0.0)):
            raise ValueError("priority errors must be finite and non-negative")
        self.max_priority = max(self.max_priority, float(errors.max()) + self.epsilon)
        self.tree.set(slots, self.leaf_values(errors))

    def sample(self, uniforms: np.ndarray, slots: np.ndarray, probabilities: np.ndarray) -> None:
        """Stratified draw: batch segment k of the total mass gets target (k + u_k) ·
        total / batch, u_k uniform in [0, 1) (`uniforms`); the drawn slots and their P(i)
        are written into `slots` and `probabilities`."""
        total = self.tree.total
        batch = len(uniforms)
        targets = (np.arange(batch) + uniforms) * (total / batch)
        # (k + u) / batch * total may round up to total itself: the largest float below it.
        np.minimum(targets, np.nextafter(total, 0.0), out=targets)
        slots[...] = self.tree.find(targets)
        np.divide(self.tree.leaves[slots], total, out=probabilities)

    def state_dict(self) -> dict[str, Any]:
        """The leaves (a tensor: checkpoints hold tensors) and the running maximum; the
        sums are rebuilt on load."""
        return {
            "leaves": torch.from_numpy(self.tree.leaves.copy()),
            "max_priority": self.max_priority,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.tree.load(state["leaves"].cpu().numpy())
        self.max_priority = float(state["max_priority"])


def measure_sampling(
    capacity: int = 1_000_000,
    batch_size: int = 32,
    repeats: int = 2000,
    seed: int = 0,
    fanout: int = FANOUT,
) -> dict[str, float]:
    """Median microseconds of a prioritized minibatch draw (stratified descent, P(i),
    importance weights) and of the priority update that follows it, on a full tree of
    `capacity` random priorities: the replay's part of one prioritized update."""
    rng = np.random.default_rng(seed)
    priorities = ProportionalPriorities(capacity, exponent=0.6, epsilon=1e-6, fanout=fanout)
    priorities.tree.load(priorities.leaf_values(rng.exponential(size=capacity)))
    uniforms = np.empty(batch_size)
    slots = np.empty(batch_size, dtype=np.int64)
    probabilities = np.empty(batch_size)
    weights = np.empty(batch_size, dtype=np.float32)
    errors = rng.exponential(size=(repeats, batch_size))
    sample_us, update_us = [], []
    for repeat in range(repeats):
        began = time.perf_counter()
        rng.random(out=uniforms)
        priorities.sample(uniforms, slots, probabilities)
        importance_weights(probabilities, capacity, 0.4, out=weights)
        sampled = time.perf_counter()
        priorities.update(slots, errors[repeat])
        updated = time.perf_counter()
        sample_us.append((sampled - began) * 1e6)
        update_us.append((updated - sampled) * 1e6)
    totals = [a + b for a, b in zip(sample_us, update_us, strict=True)]
    return {
        "capacity": capacity,
        "batch_size": batch_size,
        "fanout": fanout,
        "depth": priorities.tree.depth,
        "sample_us": statistics.median(sample_us),
        "update_us": statistics.median(update_us),
        "total_us": statistics.median(totals),
    }
