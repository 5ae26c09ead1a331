"""Re-running a recorded job offline through perception and a planner (``mode: replay``).

A replayed job plays the recording's frames and poses (``drivers.depth.replay``, ``drivers.arm.replay``)
on the simulated clock, in recorded time, through the perception of the cell file given and a planner.
Nothing moves, so the planner cannot choose its views: the recording's motion plays instead of what it
asks, and :class:`ReplaySession` writes every request to ``planner_requests.csv``:

- ``move_to_sensor_pose`` records the pose asked for and lets the recording play until its next frame
  is due (the recorded arm reaching its next view), then returns True; the planner's ``capture`` gets
  that frame, with the flange pose recorded at its time;
- while the planner asks what the live job's did (the same views, in order), a move and a reach check
  (``sensor_view_reachable``) get the live job's answers instead (its ``planner_requests.csv``,
  :mod:`cell.jobs.requests`): a move plays the recording until the live move ended and returns whether
  it reached its view (a refused one counted and logged with the guard's reason, as live), a reach check
  returns the live verdict. The arm's answers are not in the frames: without them a replay of LR-NBV
  asked for other views from the first move the live arm refused, and settled a planner's wait after
  each move a second time, reading the arm's pose on its way to the next view. Once the planner asks for
  something else, the recording plays on as above, and reach checks are answered from the recorded
  joints (``joints.csv``; from home's for a job recorded without them);
- likewise the guard's refusals of streamed twists: at the control tick the live guard refused one, the
  replay's guard refuses it (``MotionGuard.refuse_twist``, with the live reason), and a ``retrace`` that
  follows plays the recording until the live retrace ended and returns its answer. Without them a
  VS-Local replay of a scan whose twist was refused (``link6 would touch table``) servoed on, without
  the back-off and the blocked direction the live planner took on, and converged 2 s and one capture
  sooner, its cloud another. A job recorded before refusals were (no ``refusal`` column) replays without
  them: the log and ``result.json`` (``replay.refusals_recorded``) say so, and from a refusal the live
  arm made it may diverge;
- the replayed arm reports the joints the live arm reported at each tick (``joints.csv``), so that the
  planner's joint-limit and singularity rows (``joint_limit_twists``, ``singularity_twists``) are the
  live planner's: without them the VS-Local cube scan refused at 30.73 s (``link1 would touch link5b``)
  remembered another refused direction than the live one, whose g a joint's margin had projected out,
  and converged 13 s sooner;
- ``command_sensor_twist`` and ``hold`` record the twist asked for; the twist returned is the recorded
  sensor twist over the last control period, what the sensor really does;
- with continuous capture on, every recorded frame is captured when the clock reaches its time.

What a planner decides from real data is thus on record (its requests, its termination and the reason,
H_ROI, the packing result), and so is what perception makes of the frames with other parameters. The job
ends when the planner ends, when the recording runs out (``RecordingEnded``) or with the time budget.
The barrier queries (``feasible_sensor_velocity``, ``sensor_pose_allowed``) answer for the cell file's
planes, as in a live job.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cell.config.load import load_config
from cell.config.models import CellConfig
from cell.jobs.rebuild import RecordedResult, job_cell_file, recorded_result
from cell.jobs.requests import REACHABLE, REACHED, RecordedAnswer, pose_cells, recorded_answers
from cell.jobs.session import JobSession, ScanLimitReached, view_name
from cell.planning.base import Array
from cell.safety.events import Refusal
from drivers.arm.replay import ReplayArm
from drivers.depth.replay import TIME_TOLERANCE_S, JobRecording, ReplaySensor
from drivers.errors import ConfigError, JobError
from drivers.transforms import pose_error


class RecordingEnded(ScanLimitReached):
    """Every recorded frame and pose has been played."""


class ReplaySession(JobSession):
    """A ``ScanSession`` over a recording (see the module docstring). The arm and sensor are the replay
    backends of one job folder; the guard answers barrier queries and watches for an operator stop."""

    def __init__(self, config: CellConfig, *, arm: ReplayArm, sensor: ReplaySensor, **kwargs: Any) -> None:
        self._replay_arm = arm
        self._replay_sensor = sensor
        self._continuous = False
        super().__init__(config, sensor=sensor, **kwargs)
        self.n_planner_requests = 0
        recorded = recorded_answers(sensor.recording.job_dir)
        self._answers = recorded.answers
        self.refusals_recorded = recorded.refusals
        self._asked: dict[str, int] = {}
        self._following = bool(self._answers)
        self.n_recorded_answers = 0
        if self._following and not self.refusals_recorded:
            self.log("the recorded job was recorded before the arm's refusals of streamed twists were: where "
                     "its arm refused one, this replay's does not, and from there it may diverge")
        if self._following and self._jointed_state() is None:
            self.log("the recorded job has no joints.csv: the replayed arm reports no joints, and where a "
                     "joint's margin shaped the live planner's motion, this replay may diverge")

    def survey(self) -> None:
        """None: the replayed sensor's frames are the live job's captures, and the replayed arm moves
        nowhere the live one did not."""

    def _request(self, t: float, kind: str, T_base_sensor: Array | None = None, v_sensor: Array | None = None,
                 answer: str = "", t_done: float | None = None, refusal: Refusal | None = None) -> None:
        self.n_planner_requests += 1
        super()._request(t, kind, T_base_sensor, v_sensor, answer, t_done, refusal)

    def _recorded(self, kind: str, T_base_sensor: Array | None) -> RecordedAnswer | None:
        """The live job's answer to this request (a ``move`` or ``reach`` of the pose (4, 4), a ``retrace``
        without one), while the planner asks what the live one did; None from the first request it did
        not ask, logged."""
        if not self._following:
            return None
        k = self._asked.get(kind, 0)
        self._asked[kind] = k + 1
        answers = self._answers.get(kind, [])
        if k < len(answers) and answers[k].pose == pose_cells(T_base_sensor):
            self.n_recorded_answers += 1
            return answers[k]
        self._following = False
        asked = f"another {kind} than the recorded job's {kind} {k + 1}" if k < len(answers) else \
            f"more {kind}s than the recorded job ({len(answers)})"
        self.log(f"the planner asked for {asked}: from here the recording plays on whatever it asks, and the "
                 "recorded answers no longer apply")
        return None

    def _guard_tick(self) -> None:
        """The live guard's refusal of a streamed twist at this tick, while the planner asks what the live
        one did; else the guard's tick."""
        refusals = self._answers.get("twist", [])
        k = self._asked.get("twist", 0)
        if self._following and k < len(refusals) and refusals[k].t <= self.now() + self._dt / 2:
            self._asked["twist"] = k + 1
            refusal = refusals[k].refusal
            if refusal is not None:
                self.n_recorded_answers += 1
                raise self._guard.refuse_twist(refusal)
        super()._guard_tick()

    def _ended(self) -> RecordingEnded:
        frames = len(self._replay_sensor.recording.frames)
        return RecordingEnded(f"recording ended: all {frames} recorded frames played")

    def _tick(self) -> None:
        due = self._replay_sensor.next_timestamp
        if self._continuous and due is not None and due <= self.now() + TIME_TOLERANCE_S:
            self._capture_continuous()
        if self.now() > self._replay_arm.end_time and self._replay_sensor.remaining == 0:
            raise self._ended()
        super()._tick()

    def set_continuous_capture(self, on: bool) -> None:
        """Capture each recorded frame when the clock reaches its time (not at the perception rate: the
        recording sets the rate), or stop doing so. The watchdog does not judge the frames' age: nothing
        moves."""
        self._continuous = on

    def _move_to_view(self, T_base_sensor: Array) -> bool:
        """With the live job's answer (:meth:`_recorded`), play the recording until the live move ended and
        return whether it reached its view; else play it until its next frame is due and return True. The
        session records the request and the answer (``move_to_sensor_pose``)."""
        recorded = self._recorded("move", T_base_sensor)
        if recorded is not None and recorded.t_done is not None:
            return self._play_answer(recorded, view_name(T_base_sensor))
        due = self._replay_sensor.next_timestamp
        if due is None:
            self._request(self.now(), "move", T_base_sensor)  # asked, and unanswered: the recording has ended
            raise self._ended()
        while self.now() < due - self._dt:
            self._tick()
        return True

    def _retrace(self, duration_s: float) -> bool:
        """The live retrace's answer while the planner follows the live one (:meth:`_play_answer`), else
        False: a replayed arm cannot go back along its path."""
        recorded = self._recorded("retrace", None)
        if recorded is None or recorded.t_done is None:
            return False
        return self._play_answer(recorded, f"retrace of {duration_s:g} s")

    def _play_answer(self, recorded: RecordedAnswer, what: str) -> bool:
        """Play the recording until the live move or retrace ``recorded`` ended; whether it reached its
        goal, a refusal counted and logged as the live one was (``what`` names it)."""
        assert recorded.t_done is not None
        while self.now() < recorded.t_done - self._dt / 2:
            self._tick()
        if recorded.refusal is not None:
            self._refused(recorded.refusal, what)
        return recorded.answer == REACHED

    def _view_reachable(self, T_base_sensor: Array) -> bool:
        """The live job's verdict on the view while the planner follows it (:meth:`_recorded`), else the
        session's own (seeded from the recorded joints, or home's for a job recorded without them)."""
        recorded = self._recorded("reach", T_base_sensor)
        if recorded is None:
            return super()._view_reachable(T_base_sensor)
        return recorded.answer == REACHABLE

    def capture(self) -> int:
        """The next recorded frame due (waiting for its time) through perception, with the flange pose
        recorded at the frame's time."""
        if self._replay_sensor.remaining == 0:
            raise self._ended()
        frame = self._replay_sensor.capture()
        return self._ingest(frame, self._replay_arm.pose_at(frame.timestamp))

    def command_sensor_twist(self, v_sensor: Array) -> Array:
        """Record the twist asked for (sensor frame); returns the recorded sensor twist over the last
        control period [m/s, rad/s], sensor frame."""
        self._streamed = np.asarray(v_sensor, dtype=float)
        self._request(self.now(), "twist", v_sensor=self._streamed)
        return self._recorded_twist()

    def hold(self) -> None:
        self._request(self.now(), "hold")

    def _recorded_twist(self) -> Array:
        t = self.now()
        T1 = self._replay_arm.pose_at(t) @ self._T_flange_sensor
        T0 = self._replay_arm.pose_at(t - self._dt) @ self._T_flange_sensor
        step = pose_error(T0, T1) / self._dt  # base frame
        R1 = T1[:3, :3]
        return np.concatenate([R1.T @ step[:3], R1.T @ step[3:]])


def recorded_job(job_dir: Path, config: Path | None) -> tuple[CellConfig, RecordedResult, Path]:
    """A job folder's result (its ``result.json``, or one rebuilt from ``job.json`` and the frames when
    that is missing or unreadable: :func:`cell.jobs.rebuild.recorded_result`, nothing written) and the
    cell file to replay it with (:func:`cell.jobs.rebuild.job_cell_file`: ``config``, else the one the
    job names; ``JobError`` when that is not found). Returns the loaded cell file, the result and the cell
    file's path."""
    recorded = recorded_result(job_dir)
    config = job_cell_file(job_dir, recorded.result, config)
    return load_config(config), recorded, config


def check_recording(job_dir: Path) -> None:
    """Refuse to replay a job whose frames cannot all be read (``JobError`` naming the first): a replay
    re-runs the job's planner on every recorded frame in recorded time, and one left out would change
    what it decides. ``cell reprocess`` and ``cell sensor replay`` skip such a frame instead. Its poses
    (``trajectory.csv``) are read too, so that a damaged row is refused here, before the replay's folder
    exists."""
    recording = JobRecording(job_dir)
    recording.flange_track()
    if recording.unreadable:
        path, reason = recording.unreadable[0]
        raise JobError(f"{path}: not a readable frame ({reason}); {len(recording.unreadable)} of the job's "
                       f"{len(recording.unreadable) + len(recording.frames)} frames cannot be read and a "
                       "replay plays them all (cell reprocess and cell sensor replay skip them)")


def replay_config(cfg: CellConfig, job_dir: Path) -> CellConfig:
    """``cfg`` with its arm and sensor replaced by the replay backends of ``job_dir`` (``mode: replay``),
    the sensor keeping ``cfg``'s range (the folder does not hold it)."""
    data = cfg.model_dump()
    sensor = data["sensor"]
    data.update(mode="replay",
                arm={"type": "replay", "model": cfg.arm.model, "job_dir": str(job_dir)},
                sensor={"type": "replay", "job_dir": str(job_dir),
                        **{k: sensor[k] for k in ("range_min_m", "range_max_m") if k in sensor}})
    try:
        return CellConfig.model_validate(data)
    except ValueError as exc:
        raise ConfigError(f"cannot replay with this cell file: {exc}") from None
