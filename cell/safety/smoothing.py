"""Jerk-limited smoothing of streamed twists with ruckig's velocity interface (safety issue, item 4).

Each control tick, the twist a planner asks for becomes ruckig's target velocity and the smoother returns
the next twist to send: reached with bounded acceleration and jerk, in phase synchronisation so that the
twist changes along a straight line in velocity space (the direction of a change is kept). Per-axis limits
are the Cartesian limits divided by sqrt(3), so that the norm of the linear (angular) acceleration and jerk
never exceeds the cell's limits.

The smoother also tells how the motion would come to rest from where it is (:meth:`TwistSmoother.braking`):
ruckig's time-optimal ramp to a zero twist under the same limits, which is the path a stop takes, so that
the guard can check that path before it sends a twist (``cell.safety.guard``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from ruckig import (
    ControlInterface,
    InputParameter,
    OutputParameter,
    Result,
    Ruckig,
    Synchronization,
    Trajectory,
)

from drivers.errors import SafetyStop

Array = NDArray[np.float64]

_SQRT3 = float(np.sqrt(3.0))


class TwistSmoother:
    """Ruckig in velocity control over the six twist components (v [m/s], w [rad/s]).

    ``period_s``: the control period; ``acc``/``jerk``: (linear, angular) limits as norms
    [m/s^2, rad/s^2] and [m/s^3, rad/s^3].
    """

    def __init__(self, period_s: float, acc: tuple[float, float], jerk: tuple[float, float]) -> None:
        self._otg = Ruckig(6, period_s)
        self._inp = InputParameter(6)
        self._out = OutputParameter(6)
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.synchronization = Synchronization.Phase
        inp.max_acceleration = [acc[0] / _SQRT3] * 3 + [acc[1] / _SQRT3] * 3
        inp.max_jerk = [jerk[0] / _SQRT3] * 3 + [jerk[1] / _SQRT3] * 3
        inp.max_velocity = [1e3] * 6  # not used by the velocity interface; ruckig wants a value
        self._period = period_s
        self._brake_inp = InputParameter(6)
        for name in ("control_interface", "synchronization", "max_acceleration", "max_jerk", "max_velocity"):
            setattr(self._brake_inp, name, getattr(inp, name))
        self._brake_inp.target_velocity = [0.0] * 6
        self._brake_inp.target_acceleration = [0.0] * 6
        self._brake = Trajectory(6)
        self.reset()

    def reset(self) -> None:
        """Restart from rest with zero acceleration (after a stop)."""
        inp = self._inp
        inp.current_position = [0.0] * 6
        inp.current_velocity = [0.0] * 6
        inp.current_acceleration = [0.0] * 6
        inp.target_velocity = [0.0] * 6
        inp.target_acceleration = [0.0] * 6

    def scale(self, factor: float) -> Array:
        """Scale the current twist and acceleration by ``factor`` (0, 1] (a limit applied after smoothing);
        keeping the acceleration keeps a braking ramp going. Returns the scaled twist."""
        inp = self._inp
        inp.current_velocity = (np.array(inp.current_velocity) * factor).tolist()
        inp.current_acceleration = (np.array(inp.current_acceleration) * factor).tolist()
        return np.array(inp.current_velocity)

    def snapshot(self) -> tuple[list[float], list[float]]:
        """The current twist and its rate of change, to :meth:`restore` after a step that is not taken."""
        return list(self._inp.current_velocity), list(self._inp.current_acceleration)

    def restore(self, snapshot: tuple[list[float], list[float]]) -> None:
        """Go back to a :meth:`snapshot`."""
        self._inp.current_velocity, self._inp.current_acceleration = list(snapshot[0]), list(snapshot[1])

    def blend(self, snapshot: tuple[list[float], list[float]], share: float) -> Array:
        """Take only ``share`` [0, 1] of the step since ``snapshot``: the twist and its rate of change go back
        that far towards the snapshot's (a limit applied after smoothing). Returns the twist."""
        v0, a0 = np.array(snapshot[0]), np.array(snapshot[1])
        inp = self._inp
        inp.current_velocity = (v0 + share * (np.array(inp.current_velocity) - v0)).tolist()
        inp.current_acceleration = (a0 + share * (np.array(inp.current_acceleration) - a0)).tolist()
        return np.array(inp.current_velocity)

    def braking(self) -> tuple[Array, Array]:
        """How the current twist comes to rest: it is sent for one control period (the step it came from),
        then ruckig's time-optimal ramp to zero under the same limits and synchronisation runs. Returns the
        times (k,) [s] from now, about one control period apart, and the twist (k, 6) at each; the first
        sample is now, the last the arm at rest."""
        inp = self._brake_inp
        v0 = np.array(self._inp.current_velocity)
        inp.current_position = [0.0] * 6
        inp.current_velocity = self._inp.current_velocity
        inp.current_acceleration = self._inp.current_acceleration
        result = self._otg.calculate(inp, self._brake)
        if result not in (Result.Working, Result.Finished):
            raise SafetyStop(f"braking ramp failed ({result})")
        duration = self._brake.duration
        ramp = np.append(np.arange(0.0, duration, self._period), duration)
        times = np.concatenate([[0.0], ramp + self._period])
        twist = np.vstack([v0, np.array([self._brake.at_time(t)[1] for t in ramp])])
        return times, twist

    def step(self, target: Array) -> Array:
        """One control period towards ``target``; returns the twist to send now."""
        self._inp.target_velocity = np.asarray(target, dtype=float).tolist()
        result = self._otg.update(self._inp, self._out)
        if result not in (Result.Working, Result.Finished):
            raise SafetyStop(f"velocity smoothing failed ({result})")
        self._out.pass_to_input(self._inp)
        # Positions are irrelevant to a velocity stream; keep them at zero so they never grow large.
        self._inp.current_position = [0.0] * 6
        return np.array(self._out.new_velocity)
