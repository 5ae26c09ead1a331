"""What the simulated depth sensors share: the scene, the true pose they render from, the job's clock and
generator, the connection state and the frame counter."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from drivers.clock import Clock
from drivers.depth.base import DepthSensor
from drivers.errors import DriverError
from drivers.local_link import LocalLink
from drivers.sim.scene import SimScene

Array = NDArray[np.float64]


class SimDepthSensor(LocalLink, DepthSensor):
    """Base of the ray-cast sensors. ``pose_source()`` returns the true T_base_sensor (4x4) at capture
    time; ``clock`` stamps frames; ``rng`` is the only source of noise; ``depth_offset_m`` [m] a bias
    added to every range the sensor reports (``drivers.sim.errors``)."""

    def __init__(self, scene: SimScene, pose_source: Callable[[], Array], clock: Clock,
                 rng: np.random.Generator, depth_offset_m: float = 0.0) -> None:
        self.depth_offset_m = depth_offset_m
        self._scene = scene
        self._pose_source = pose_source
        self._clock = clock
        self._rng = rng
        self._seq = 0
        self._stalled_until = -np.inf

    def _begin_capture(self) -> Array:
        """Check the sensor is connected and return the true, finite T_base_sensor to render from."""
        self._require_connected("capture", self.name)
        if self._clock.now() < self._stalled_until:
            raise DriverError("no frame: the sensor stopped delivering (simulated stall)", device=self.name)
        T = np.asarray(self._pose_source(), dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DriverError(f"pose source returned an invalid T_base_sensor (shape {T.shape})",
                              device=self.name)
        return T

    def stall(self, duration_s: float) -> None:
        """Deliver no frame for ``duration_s`` seconds from now (a simulated sensor fault)."""
        self._stalled_until = self._clock.now() + duration_s

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq += 1
        return seq
