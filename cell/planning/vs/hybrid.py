"""VS-Hybrid (visual-servoing paper section II-D): VS-Local until its gradient converges (eq. 4-6 and the
||g|| window), then one VS-Global goal (eq. 10-11) to leave a possible local maximum, then local again
with a fresh window, and so on. The scan ends on the H_ROI rule of eq. 12, as VS-Global's, judged on the
values recorded after the first global goal was reached or given up (not in the paper, which does not say
whether the rule already applies to the first local phase and the way to the first goal)."""

from __future__ import annotations

from cell.config.models import CellConfig
from cell.planning.base import Array, ScanSession
from cell.planning.vs.goals import GoalSeeker
from cell.planning.vs.local import LocalGradient
from cell.planning.vs.objective import EntropyObjective
from cell.planning.vs.servo_scan import Secondary, ServoScanPlanner


class VSHybridPlanner(ServoScanPlanner):
    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        self.local = LocalGradient(config, coarse=False)  # its global goals leave a plateau
        self.goals = GoalSeeker(config)
        self._global_leg = False

    def secondary(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective,
                  rows: Array) -> Secondary:
        if self._global_leg and self.goals.done(session, T_base_cam):
            self._global_leg = False
            self.local.reset()
            self.open_entropy_window()
        elif not self._global_leg and self.local.converged():
            assert self.centroid is not None
            self.goals.sample(session, self.centroid, objective)
            self._global_leg = True
        if self._global_leg:
            return self.goals(session, T_base_cam, objective)
        return self.local(session, T_base_cam, objective)

    def observe(self, secondary: Secondary, g_norm: float, position_m: Array) -> None:
        if secondary.mode == "local":
            self.local.record(g_norm, position_m)

    def finished(self, session: ScanSession) -> str | None:
        # The H_ROI rule is judged from the end of the first global leg on, on the values recorded since:
        # while the first local phase still climbs the gradient slowly, and while the camera travels to
        # the first goal, H_ROI can stay flat for ten perception updates, and the scan would end as a
        # Local scan stopped early (bunny: 75 % instead of 90 %).
        return self.entropy_settled()
