"""Mann-Whitney U of the evaluation report against every split of the pooled values, ties included."""

from __future__ import annotations

import itertools

import pytest
from scipy.stats import rankdata

from cell.evaluation.report import mann_whitney


def _split_p(a: list[float], b: list[float]) -> float:
    """Two-sided p of U over every way of splitting the pooled values into samples of len(a) and len(b):
    twice the smaller of the shares of splits whose U is at least and at most a's (midranks for ties), at
    most 1."""
    pooled = a + b
    ranks = rankdata(pooled)

    def u(indices: tuple[int, ...]) -> float:
        return float(sum(ranks[i] for i in indices) - len(a) * (len(a) + 1) / 2)

    observed = u(tuple(range(len(a))))
    us = [u(s) for s in itertools.combinations(range(len(pooled)), len(a))]
    above = sum(v >= observed - 1e-9 for v in us) / len(us)
    below = sum(v <= observed + 1e-9 for v in us) / len(us)
    return min(1.0, 2.0 * min(above, below))


@pytest.mark.parametrize(("a", "b"), [
    ([1, 1, 1, 2, 2], [2, 2, 3, 3, 3]),      # poses: the normal approximation said 0.027
    ([0, 0, 0, 0, 1], [0, 1, 1, 1, 1]),      # useless poses: it said 0.093
    ([5.0, 5.0, 6.0], [6.0, 7.0, 7.0]),
    ([0.91, 0.93, 0.95, 0.97, 0.99], [0.92, 0.94, 0.96, 0.98, 1.0]),  # no ties
    ([1, 1, 2], [2, 3, 3, 3, 4]),            # sizes and ties unequal: U's distribution is not symmetric
])
def test_p_is_twice_the_smaller_one_sided_share_of_splits_for_small_tied_samples(a, b):
    test = mann_whitney(a, b)
    assert test is not None
    u, p = test
    assert u == pytest.approx(sum(rankdata(a + b)[: len(a)]) - len(a) * (len(a) + 1) / 2)
    assert p == pytest.approx(_split_p(a, b), abs=1e-12)


def test_large_samples_keep_a_p_without_enumerating_every_split():
    a = [float(v) for v in range(20)]
    b = [v + 10.5 for v in a]
    test = mann_whitney(a, b)
    assert test is not None and 0.0 < test[1] < 0.05
