"""The watchdog: a late control loop or stale perception stops the arm (safety issue, item 5).

Times are job times [s] (sim time in sim mode, the monotonic wall clock in real mode), so the same rules
hold in both: in sim a late loop is simulated (``sim.faults``), on hardware it is real.
"""

from __future__ import annotations

from cell.safety.config import WatchdogConfig


class Watchdog:
    """Counts control ticks that miss their deadline and judges the age of perception data.

    ``period_s`` is the control period. :meth:`tick` and :meth:`perception` return the reason to stop,
    in words, or None.
    """

    def __init__(self, config: WatchdogConfig, period_s: float) -> None:
        self._cfg = config
        self._deadline = config.deadline_factor * period_s
        self._last_tick: float | None = None
        self.missed_in_a_row = 0

    def tick(self, now: float) -> str | None:
        """Record a control tick at ``now``."""
        last, self._last_tick = self._last_tick, now
        if last is None:
            return None
        gap = now - last
        if gap <= self._deadline + 1e-9:
            self.missed_in_a_row = 0
            return None
        self.missed_in_a_row += 1
        if self.missed_in_a_row >= self._cfg.max_missed_deadlines:
            return (f"control loop missed its deadline {self.missed_in_a_row} times in a row (last tick "
                    f"{gap * 1e3:.1f} ms after the previous one, deadline {self._deadline * 1e3:.1f} ms)")
        return None

    def perception(self, now: float, newest_data_s: float | None) -> str | None:
        """Judge perception data taken at ``newest_data_s`` (None: none yet) while motion depends on it."""
        if newest_data_s is None:
            return None
        age = now - newest_data_s
        if age > self._cfg.perception_max_age_s:
            return (f"perception data are {age:.2f} s old (limit {self._cfg.perception_max_age_s:g} s) "
                    "while motion depends on them")
        return None
