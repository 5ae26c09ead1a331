"""Per-tick records of a job in bounded memory: a series decimated by halving as it grows.

A job keeps some records per control tick (the servo telemetry of Fig. 4, the sensor path, the tick
periods), for the plots and figures written at its end. A one-hour job at 500 Hz has 1.8 million ticks,
so each such series is a :class:`DecimatedSeries`: it keeps every record until ``capacity``; at capacity
it drops every other kept record and from then on keeps only every ``stride``-th record offered, the
stride doubling at each halving. The kept records are thus always those whose index (0-based, in the
order offered) is a multiple of the stride: evenly spaced over the whole job, the first included, at most
``capacity`` of them, and the newest is kept besides. A job shorter than ``capacity`` ticks keeps
everything, as without decimation. Deterministic: the same records give the same series.
"""

from __future__ import annotations

from typing import Generic, TypeVar

T = TypeVar("T")

SERIES_CAPACITY = 1 << 15
"""Records a per-tick series keeps before it is halved: 32768, 4.4 min at 125 Hz (a normal 180 s scan is
never decimated), a few MiB per series."""


class DecimatedSeries(Generic[T]):
    """A series of at most ``capacity`` (default ``SERIES_CAPACITY``) evenly spaced records, plus the newest
    (see the module docstring)."""

    def __init__(self, capacity: int | None = None) -> None:
        capacity = SERIES_CAPACITY if capacity is None else capacity
        if capacity < 2:
            raise ValueError(f"a decimated series needs a capacity of at least 2, got {capacity}")
        self.capacity = capacity
        self.stride = 1
        self.count = 0
        """How many records were offered (kept or not)."""
        self._kept: list[T] = []
        self._last: T | None = None

    def append(self, record: T) -> None:
        if self.count % self.stride == 0:
            if len(self._kept) == self.capacity:
                del self._kept[1::2]
                self.stride *= 2
            if self.count % self.stride == 0:
                self._kept.append(record)
        self._last = record
        self.count += 1

    @property
    def last(self) -> T:
        """The newest record; ``IndexError`` when there is none."""
        if self.count == 0:
            raise IndexError("the series is empty")
        return self._last  # type: ignore[return-value]

    @property
    def _newest_dropped(self) -> bool:
        """Whether the newest record fell between the kept ones (``records`` adds it at the end)."""
        return self.count > 0 and (self.count - 1) % self.stride != 0

    def records(self) -> list[T]:
        """The kept records in order, ending with the newest record."""
        return [*self._kept, self.last] if self._newest_dropped else list(self._kept)

    def __len__(self) -> int:
        """How many records :meth:`records` returns (not how many were offered: see ``count``)."""
        return len(self._kept) + self._newest_dropped

    def __bool__(self) -> bool:
        return self.count > 0
