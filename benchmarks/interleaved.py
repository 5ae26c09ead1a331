"""What the benchmarks that time this tree against a reference share (a helper module of theirs, not a
benchmark: running it does nothing): the order of the two in a repeat, and their figures side by side.

Each repeat times both, in turn, the one that runs first alternating from repeat to repeat, so that
neither always meets the caches and the machine's load the other left; the figure of each is the median
over the repeats, the ratio that of the medians, and the spread of the repeats' own ratios is given
beside it (one ratio of a shared machine hides how far it moves).
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from typing import NamedTuple, TypeVar

T = TypeVar("T")


def in_turn(repeat: int, sides: Sequence[T]) -> list[T]:
    """``sides`` in the order they run in repeat ``repeat`` (from 0): as given in even repeats, reversed
    in odd ones."""
    return list(sides[::-1] if repeat % 2 else sides)


class Comparison(NamedTuple):
    """Medians of this tree's and the reference's figures, their ratio (this / reference), and the
    smallest and largest ratio of one repeat's two figures."""

    this: float
    reference: float
    ratio: float
    ratio_min: float
    ratio_max: float

    def ratios(self) -> dict[str, float | list[float]]:
        """{"ratio": R, "ratio_range": [R1, R2]}, to 3 decimals, for a benchmark's JSON."""
        return {"ratio": round(self.ratio, 3),
                "ratio_range": [round(self.ratio_min, 3), round(self.ratio_max, 3)]}

    def text(self, digits: int = 3) -> str:
        """``ratio R (repeats R1-R2)``."""
        low, high = (f"{r:.{digits}f}" for r in (self.ratio_min, self.ratio_max))
        return f"ratio {self.ratio:.{digits}f} (repeats {low}-{high})"


def compared(this: Sequence[float], reference: Sequence[float]) -> Comparison:
    """``this`` against ``reference``: one figure per repeat each, of the same repeats."""
    ratios = [t / r for t, r in zip(this, reference, strict=True)]
    mine, theirs = statistics.median(this), statistics.median(reference)
    return Comparison(mine, theirs, mine / theirs, min(ratios), max(ratios))
