"""Perception on the wall clock: frames captured on their own thread, paired with the poses the control
loop recorded, processed asynchronously, recorded by the worker; the control loop polls updates."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.config import load_config
from cell.jobs.live import LivePerception, PoseHistory
from cell.perception.pipeline import PerceptionPipeline
from drivers.clock import WallClock
from drivers.depth.base import DepthFrame
from drivers.depth.sim_tof import SimToF
from drivers.errors import DeviceFault, DriverError
from drivers.scheduling import is_realtime, ordinary_scheduling
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at, make_T

from .conftest import UR5E, wait_for


def _pose(x: float, yaw_deg: float) -> np.ndarray:
    return make_T(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), np.array([x, 0.0, 0.3]))


def test_pose_history_interpolates_between_the_recorded_poses() -> None:
    poses = PoseHistory(maxlen=3)
    with pytest.raises(DriverError, match="no arm pose"):
        poses.at(0.0)
    poses.add(1.0, _pose(0.0, 0.0))
    poses.add(2.0, _pose(0.1, 20.0))
    T = poses.at(1.25)
    np.testing.assert_allclose(T[:3, 3], [0.025, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], _pose(0.0, 5.0)[:3, :3], atol=1e-12)
    np.testing.assert_array_equal(poses.at(0.5), _pose(0.0, 0.0))  # before the first: the first
    np.testing.assert_array_equal(poses.at(9.0), _pose(0.1, 20.0))  # after the newest: the newest
    for t in (3.0, 4.0):
        poses.add(t, _pose(t, 0.0))
    np.testing.assert_array_equal(poses.at(1.5), _pose(0.1, 20.0))  # the oldest pose has gone
    np.testing.assert_array_equal(poses.latest(), _pose(4.0, 0.0))


class _FlakySensor:
    """The simulated ToF on the wall clock, failing its first ``failures`` captures."""

    def __init__(self, sensor: SimToF, failures: int) -> None:
        self._sensor = sensor
        self.failures = failures
        self.device = "flaky sim-tof"

    def capture(self) -> DepthFrame:
        if self.failures:
            self.failures -= 1
            raise DriverError("no frame", device=self.device)
        time.sleep(0.02)  # a 50 Hz sensor
        return self._sensor.capture()


@pytest.fixture
def live_rig():
    cfg = load_config(UR5E)
    clock = WallClock()
    T_base_flange = look_at(np.array([0.25, -0.1, 0.3]), np.array([0.45, 0.0, 0.03]))
    T_flange_sensor = cfg.mount.matrix()
    scene = SimScene(load_object("horizontal_box"), make_T(np.eye(3), np.array([0.45, 0.0, 0.0])))
    sensor = SimToF(cfg.sensor, scene, lambda: T_base_flange @ T_flange_sensor, clock,
                    np.random.default_rng(0))
    sensor.connect()
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(1))
    poses = PoseHistory()
    poses.add(clock.now(), T_base_flange)
    return sensor, pipeline, poses, T_base_flange, T_flange_sensor


def test_live_perception_captures_processes_and_records_on_its_own_threads(live_rig) -> None:
    sensor, pipeline, poses, T_base_flange, T_flange_sensor = live_rig
    flaky = _FlakySensor(sensor, failures=2)
    recorded: list[tuple[int, np.ndarray, str]] = []
    logged: list[str] = []
    live = LivePerception(flaky, pipeline, poses, T_flange_sensor,
                          record=lambda f, T, u: recorded.append((f.seq, T, threading.current_thread().name)),
                          log=logged.append)
    live.start()
    updates = []
    try:
        assert wait_for(lambda: (u := live.poll()) is not None and updates.append(u) is None
                         and len(updates) >= 3)
    finally:
        live.stop()
    assert not any(t.name in ("capture", "perception") for t in threading.enumerate())
    assert live.n_capture_failures == 2 and logged == ["capture failed: flaky sim-tof: no frame"] * 2
    # each update is newer than the one before, and polled once
    seqs = [u.seq for u in updates]
    assert seqs == sorted(set(seqs))
    assert live.poll() is None or live.poll() is None
    # the worker recorded every processed frame with the pose of its time, on its own thread
    assert len(recorded) >= len(updates)
    for _, T, thread in recorded:
        np.testing.assert_allclose(T, T_base_flange, atol=1e-12)
        assert thread == "perception"
    np.testing.assert_allclose(updates[-1].T_base_sensor, T_base_flange @ T_flange_sensor, atol=1e-12)
    # planners get a map of their own: the worker keeps writing into the pipeline's
    assert updates[-1].map is not pipeline.map
    assert updates[-1].map.n_known > 0


def test_a_worker_error_reaches_the_control_loop(live_rig) -> None:
    sensor, pipeline, poses, _, T_flange_sensor = live_rig

    def broken(*_: object) -> None:
        raise OSError("disk full")

    live = LivePerception(sensor, pipeline, poses, T_flange_sensor, record=broken, log=lambda _: None)
    live.start()
    try:
        def raised() -> bool:
            try:
                live.poll()
            except OSError as exc:
                return str(exc) == "disk full"
            return False

        assert wait_for(raised)
    finally:
        live.stop()


class _VanishingSensor:
    """A sensor whose link went: every capture raises its latched fault."""

    device = "vanished sim-tof"

    def __init__(self) -> None:
        self.captures = 0

    def capture(self) -> DepthFrame:
        self.captures += 1
        raise DeviceFault("faulted: port vanished; reconnect to clear", device=self.device)


def test_a_sensor_fault_reaches_the_control_loop_at_its_next_poll(live_rig) -> None:
    _, pipeline, poses, _, T_flange_sensor = live_rig
    vanished, logged = _VanishingSensor(), []
    live = LivePerception(vanished, pipeline, poses, T_flange_sensor, record=lambda *_: None,
                          log=logged.append)
    live.start()
    try:
        assert wait_for(lambda: bool(logged))
        with pytest.raises(DeviceFault, match="vanished sim-tof: faulted: port vanished"):
            live.poll()
        time.sleep(0.2)  # a capture thread that retried would have counted more by now
        assert vanished.captures == 1 and live.n_capture_failures == 1
    finally:
        live.stop()


def test_perception_threads_leave_a_realtime_priority_they_inherit(live_rig) -> None:
    sensor, pipeline, poses, _, T_flange_sensor = live_rig
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))  # as libfranka does to its caller
    except PermissionError:
        pytest.skip("this user may not set a realtime priority")
    try:
        assert is_realtime()
        live = LivePerception(sensor, pipeline, poses, T_flange_sensor, record=lambda *_: None,
                              log=lambda _: None)
        live.start()
        try:
            assert wait_for(lambda: live.poll() is not None)
            policies = {t.name: os.sched_getscheduler(t.native_id) for t in threading.enumerate()
                        if t.name in ("capture", "perception") and t.native_id is not None}
        finally:
            live.stop()
    finally:
        ordinary_scheduling()
    assert policies == {"capture": os.SCHED_OTHER, "perception": os.SCHED_OTHER}
    assert not is_realtime()
