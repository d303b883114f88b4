"""Proportional prioritized replay: the sum tree, the stratified draw, importance weights
and priority updates, against numbers worked out by hand or by a plain loop."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from scipy.stats import chisquare

from dqnlab.algorithm.prioritized import (
    SMALLEST_LEAF,
    ProportionalPriorities,
    SumTree,
    importance_weights,
    measure_sampling,
)

STRICT_P = 1e-3  # chi-square tests: a fixed seed, so pass or fail is deterministic


def reference_find(leaves: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The leaf each target falls in, by a plain running sum from the left."""
    found = []
    for target in targets:
        running = 0.0
        for index, value in enumerate(leaves):
            running += value
            if target < running:
                found.append(index)
                break
        else:
            found.append(max(np.flatnonzero(leaves)))
    return np.array(found)


@pytest.mark.parametrize("fanout", [2, 3, 32])
@pytest.mark.parametrize("capacity", [1, 5, 33, 1000])
def test_totals_and_leaves_of_trees_of_any_size(fanout: int, capacity: int) -> None:
    tree = SumTree(capacity, fanout)
    assert tree.leaves.dtype == np.float64 and tree.total == 0.0
    rng = np.random.default_rng(capacity)
    values = rng.random(capacity)
    tree.set(np.arange(capacity), values)
    assert tree.total == pytest.approx(math.fsum(values), rel=1e-12)
    np.testing.assert_array_equal(tree.leaves, values)
    tree.set(np.array([capacity - 1]), np.array([0.0]))
    assert tree.total == pytest.approx(math.fsum(values[:-1]), rel=1e-12)


@pytest.mark.parametrize("fanout", [2, 32])
def test_queries_at_the_boundaries_of_leaves(fanout: int) -> None:
    tree = SumTree(6, fanout)
    tree.set(np.arange(6), np.array([1.0, 0.0, 2.0, 3.0, 0.0, 0.0]))
    below = np.nextafter
    targets = np.array([0.0, below(1.0, 0), 1.0, below(3.0, 0), 3.0, below(6.0, 0)])
    assert tree.find(targets).tolist() == [0, 0, 2, 2, 3, 3]  # never the zero leaves 1, 4, 5
    np.testing.assert_array_equal(tree.find(targets), reference_find(tree.leaves, targets))


def test_updates_move_the_sums_and_repeated_indices_keep_their_last_value() -> None:
    tree = SumTree(10, fanout=2)
    tree.set(np.arange(10), np.ones(10))
    assert tree.total == 10.0
    tree.set(np.array([3, 7, 3, 3]), np.array([5.0, 2.0, 9.0, 4.0]))  # 3 ends at 4
    assert tree.leaves[3] == 4.0 and tree.leaves[7] == 2.0
    assert tree.total == 8 * 1.0 + 4.0 + 2.0
    assert tree.find(np.array([3.0, 6.999, 7.0, 10.0])).tolist() == [3, 3, 4, 7]


def test_values_must_be_finite_and_non_negative() -> None:
    tree = SumTree(4)
    for bad in (-1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="finite and non-negative"):
            tree.set(np.array([0]), np.array([bad]))
    with pytest.raises(ValueError, match="empty"):
        tree.find(np.array([0.0]))


@pytest.mark.parametrize("fanout", [2, 32])
def test_zero_leaves_are_never_drawn_even_at_rounding_edges(fanout: int) -> None:
    """Most leaves 0, the others spread over 18 orders of magnitude: every target from
    uniform draws and from just below every leaf boundary lands on a non-zero leaf."""
    rng = np.random.default_rng(3)
    capacity = 5000
    leaves = np.zeros(capacity)
    positive = rng.choice(capacity, size=50, replace=False)
    leaves[positive] = 10.0 ** rng.uniform(-12, 6, size=50) * rng.random(50)
    tree = SumTree(capacity, fanout)
    tree.set(np.arange(capacity), leaves)
    total = tree.total
    boundaries = np.cumsum(leaves)[positive]
    targets = np.concatenate(
        [
            rng.random(200_000) * total,
            np.nextafter(boundaries, 0.0),
            boundaries,
            np.nextafter(boundaries, np.inf),
            [0.0, np.nextafter(total, 0.0)],
        ]
    )
    targets = np.clip(targets, 0.0, np.nextafter(total, 0.0))
    drawn = tree.find(targets)
    assert np.all(leaves[drawn] > 0.0)
    assert set(np.unique(drawn)) <= set(positive.tolist())


def test_loading_the_leaves_rebuilds_the_same_sums_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    tree = SumTree(3000, fanout=32)
    for _ in range(200):  # sums built piecemeal by updates
        slots = rng.integers(0, 3000, size=32)
        tree.set(slots, rng.exponential(size=32) ** 0.6)
    rebuilt = SumTree(3000, fanout=32)
    rebuilt.load(tree.leaves.copy())
    for mine, theirs in zip(tree._levels, rebuilt._levels, strict=True):
        assert mine.tobytes() == theirs.tobytes()


def draw_counts(
    priorities: ProportionalPriorities, batches: int, batch_size: int, seed: int
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uniforms = np.empty(batch_size)
    slots = np.empty(batch_size, dtype=np.int64)
    probabilities = np.empty(batch_size)
    counts = np.zeros(priorities.tree.capacity, dtype=np.int64)
    for _ in range(batches):
        rng.random(out=uniforms)
        priorities.sample(uniforms, slots, probabilities)
        np.testing.assert_allclose(
            probabilities, priorities.tree.leaves[slots] / priorities.tree.total
        )
        counts += np.bincount(slots, minlength=len(counts))
    return counts


def test_stratified_draws_follow_the_priorities_chi_square() -> None:
    """Over 3,000 batches of 32, the counts match P(i) = leaf / total (chi-square, p above
    1e-3); a uniform sampler in its place fails the same test by far."""
    rng = np.random.default_rng(0)
    priorities = ProportionalPriorities(60, exponent=0.6, epsilon=0.01)
    priorities.update(np.arange(60), rng.exponential(size=60))
    priorities.update(np.array([7, 8]), np.array([0.0, 0.0]))  # small, not zero
    counts = draw_counts(priorities, batches=3000, batch_size=32, seed=1)
    expected = priorities.tree.leaves / priorities.tree.total * counts.sum()
    assert chisquare(counts, expected).pvalue > STRICT_P
    uniform = np.bincount(rng.integers(0, 60, size=counts.sum()), minlength=60)
    assert chisquare(uniform, expected).pvalue < STRICT_P


def test_stratified_draws_take_one_transition_per_segment_of_mass() -> None:
    """Four equal leaves, a batch of four: segment k is exactly leaf k, whatever u."""
    priorities = ProportionalPriorities(4, exponent=1.0, epsilon=0.0)
    priorities.update(np.arange(4), np.full(4, 2.5))
    slots, probabilities = np.empty(4, dtype=np.int64), np.empty(4)
    for u in (0.0, 0.5, 0.999):
        priorities.sample(np.full(4, u), slots, probabilities)
        assert slots.tolist() == [0, 1, 2, 3] and probabilities.tolist() == [0.25] * 4


def test_importance_weights_by_hand() -> None:
    probabilities = np.array([0.5, 0.25, 0.125, 0.125])
    # (4 P)^-1/2 = 2^-1/2, 1, 2^1/2, 2^1/2, over the batch's largest, 2^1/2.
    half = importance_weights(probabilities, 4, 0.5)
    np.testing.assert_allclose(half, [0.5, 2**-0.5, 1.0, 1.0], rtol=1e-7)
    assert half.dtype == np.float32
    np.testing.assert_allclose(importance_weights(probabilities, 4, 1.0), [0.25, 0.5, 1, 1])
    np.testing.assert_array_equal(importance_weights(probabilities, 4, 0.0), np.ones(4))
    # N cancels out with the batch maximum.
    np.testing.assert_array_equal(importance_weights(probabilities, 10**6, 0.5), half)
    out = np.zeros(4, dtype=np.float32)
    assert importance_weights(probabilities, 4, 0.5, out=out) is out
    np.testing.assert_array_equal(out, half)


def test_priorities_are_error_plus_epsilon_to_the_alpha_and_the_maximum_is_raw() -> None:
    priorities = ProportionalPriorities(8, exponent=0.5, epsilon=0.25)
    assert priorities.max_priority == 1.0 and priorities.new_leaf == 1.0  # p_1 = 1
    priorities.update(np.array([2, 5]), np.array([3.75, 0.0]))
    assert priorities.tree.leaves[2] == 2.0  # (3.75 + 0.25)^0.5
    assert priorities.tree.leaves[5] == 0.5  # (0 + 0.25)^0.5
    assert priorities.max_priority == 4.0 and priorities.new_leaf == 2.0
    priorities.update(np.array([2]), np.array([0.75]))  # lower: the maximum stays
    assert priorities.tree.leaves[2] == 1.0 and priorities.max_priority == 4.0
    with pytest.raises(ValueError, match="non-negative"):
        priorities.update(np.array([1]), np.array([-0.5]))


def test_a_zero_error_without_epsilon_keeps_a_non_zero_leaf() -> None:
    """A valid slot's leaf is never 0: 0 is how the replay marks slots it cannot draw."""
    priorities = ProportionalPriorities(4, exponent=0.6, epsilon=0.0)
    priorities.update(np.array([1]), np.array([0.0]))
    assert priorities.tree.leaves[1] == SMALLEST_LEAF > 0.0


def test_state_round_trip_through_a_checkpoints_loader() -> None:
    rng = np.random.default_rng(6)
    priorities = ProportionalPriorities(100, exponent=0.6, epsilon=1e-6)
    priorities.update(rng.integers(0, 100, 64), rng.exponential(size=64) * 3)
    saved = io.BytesIO()
    torch.save(priorities.state_dict(), saved)
    saved.seek(0)
    loaded = ProportionalPriorities(100, exponent=0.6, epsilon=1e-6)
    loaded.load_state_dict(torch.load(saved, weights_only=True))
    assert loaded.max_priority == priorities.max_priority
    assert loaded.tree.total == priorities.tree.total
    np.testing.assert_array_equal(
        draw_counts(loaded, 20, 32, 9), draw_counts(priorities, 20, 32, 9)
    )


def test_the_benchmark_measures_a_draw_and_an_update() -> None:
    figures = measure_sampling(capacity=1000, batch_size=8, repeats=5, fanout=4)
    assert figures["depth"] == 5 and figures["fanout"] == 4
    assert figures["sample_us"] > 0 and figures["update_us"] > 0
