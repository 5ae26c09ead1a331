"""What the benchmarks that time this tree against a reference share (a helper module of theirs, not a
benchmark: running it does nothing): the order of the two in a repeat, and their figures side by side.

Each repeat times both, in turn, the one that runs first alternating from repeat to repeat, so that
neither always meets the caches and the machine's load the other left; the figure of each is the median
over the repeats, the ratio the median of the repeats' own ratios (this / reference of one repeat, two
figures measured side by side: the pairing the interleaving is for), and their spread is given beside it
(one ratio of a shared machine hides how far it moves).
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
    """Medians of this tree's and the reference's figures, and the median, smallest and largest of the
    repeats' own ratios (this / reference of one repeat)."""

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
    return Comparison(statistics.median(this), statistics.median(reference), statistics.median(ratios),
                      min(ratios), max(ratios))
