"""A simulated cell driven through the real safety guard, and a judge of the motion it made that shares no
code with the guard (used by the safety tests and by ``benchmarks/safety_soak.py``).

:func:`cell_config` is one of the sim cell files with other start joints, more barrier planes and
obstacles; :class:`Rig` builds that cell as a job does (robot model, the simulated arm from the arm
factory, ``MotionGuard.from_config``). :class:`MotionJudge` watches the joints the simulated arm really
took, one sample per control period, and counts what the safety layer must prevent. It knows the cell
only from its config and the robot model (forward kinematics, capsules, limits): barrier planes are
point-normal pairs, contacts come from python-fcl on bodies it builds itself, and speeds, accelerations
and jerks are finite differences of the realized joints and flange poses. A guard whose projection,
collision check or joint clamp is missing or wrong shows here, whatever the guard believes.
"""

from __future__ import annotations

import copy
import functools
from collections import Counter
from pathlib import Path
from typing import Any

import fcl
import numpy as np
from numpy.typing import NDArray

from cell.config import load_config
from cell.config.load import parse_config
from cell.config.models import CellConfig
from cell.safety.guard import SPEED_SLACK, MotionGuard
from drivers.arm.base import ArmMode
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.factory import SimWorld, make_arm
from drivers.robots import get_robot_model
from drivers.robots.model import RobotModel
from drivers.transforms import rotvec
from tests.conftest import FRANKA, UR5E

Array = NDArray[np.float64]

CELLS: dict[str, Path] = {"panda": FRANKA, "ur5e": UR5E}

# Finite differences of a motion planned exactly at a limit land on it up to rounding.
RATE_SLACK = 1e-6
# The guard lets a sampled trajectory's flange speed exceed its limit by this factor (its finite differences
# are checked "a hair above the planned bound"); the judge holds it to the same.
TRAJECTORY_SPEED_ALLOWANCE = 1.02
# A joint this close to its limit [rad] has reached it (the simulated arm clamps there; a real one faults).
AT_LIMIT_RAD = 1e-6


@functools.cache
def _cell_file(model_name: str) -> dict[str, Any]:
    return load_config(CELLS[model_name]).model_dump(mode="json")


def cell_config(model_name: str, *, home_joints_rad: Array | list[float] | None = None,
                barrier_planes: list[dict[str, Any]] | None = None,
                obstacles: list[dict[str, Any]] | None = None) -> CellConfig:
    """The sim cell file of ``model_name`` (``panda`` or ``ur5e``), validated again as a job's worker
    does, with the arm starting at ``home_joints_rad`` [rad], ``barrier_planes`` (``point``, ``normal``,
    ``name``; base frame) added to the file's own, and ``obstacles`` (collision bodies, base frame) in
    place of the file's."""
    data = copy.deepcopy(_cell_file(model_name))
    if home_joints_rad is not None:
        data["arm"]["home_joints_rad"] = [float(x) for x in home_joints_rad]
    data["safety"]["barrier_planes"] += barrier_planes or []
    if obstacles is not None:
        data["safety"]["collision"]["obstacles"] = obstacles
    return parse_config(data, file=str(CELLS[model_name]))


class Rig:
    """A cell's simulated arm driven by its guard. Records every twist that reaches the backend (``sent``)
    and shows every joint sample the arm takes to its ``judge``."""

    def __init__(self, cfg: CellConfig) -> None:
        self.cfg = cfg
        self.model = get_robot_model(cfg.arm.model)
        self.clock = SimClock()
        arm = make_arm(cfg.arm, self.model, SimWorld(clock=self.clock, rng=np.random.default_rng(0),
                                                      scene=None))
        assert isinstance(arm, SimArm)
        self.arm = arm
        arm.connect()
        self.guard = MotionGuard.from_config(arm, self.model, cfg, self.clock)
        self.dt = 1.0 / cfg.scan.control_rate_hz
        self.sent: list[Array] = []
        # Where each twist of ``sent`` was sent: the time [s] and the arm's joints [rad].
        self.sent_at: list[tuple[float, Array]] = []
        backend = arm._command_twist

        def record(v: np.ndarray) -> None:
            self.sent.append(np.array(v))
            self.sent_at.append((self.clock.now(), arm.state().q))
            backend(v)

        arm._command_twist = record  # type: ignore[method-assign,assignment]
        self.judge = MotionJudge(cfg, self.model, self.dt)
        self.judge.start(arm.state().q)

    @classmethod
    def of(cls, model_name: str, home_joints_rad: list[float] | tuple[float, ...] | None = None) -> Rig:
        """The rig of a robot's sim cell file, optionally starting elsewhere."""
        return cls(cell_config(model_name, home_joints_rad=None if home_joints_rad is None
                               else list(home_joints_rad)))

    def set_roi(self, aabb_min: Array, aabb_max: Array) -> None:
        """The object's box (base frame [m]) for the guard and the judge alike."""
        self.guard.set_roi(aabb_min, aabb_max)
        self.judge.set_roi(aabb_min, aabb_max)

    def step(self) -> None:
        """One control period of simulated time; the judge sees the joints the arm reached."""
        mode = self.arm.state().mode
        self.clock.sleep(self.dt)
        self.judge.observe(self.arm.state().q, mode)

    def tick(self, n: int = 1) -> None:
        """``n`` control periods, each with the guard's tick."""
        for _ in range(n):
            self.guard.tick()
            self.step()

    def settle(self, max_steps: int = 500) -> None:
        """Let the arm come to rest after a stop, commanding nothing."""
        for _ in range(max_steps):
            state = self.arm.state()
            if state.mode in (ArmMode.IDLE, ArmMode.FAULT) and not np.any(state.qd):
                return
            self.step()
        raise AssertionError(f"the arm did not come to rest within {max_steps} control periods")

    def assert_safe(self) -> None:
        """No breach so far (the judge's counts and worst values name what went wrong)."""
        breaches = {k: v for k, v in self.judge.breaches.items() if v}
        assert not breaches, f"breaches (samples): {breaches}; worst: {self.judge.worst}"

    def commanded(self) -> dict[str, Array]:
        """Each streaming limit of the cell file as the guard defines it, judged on the twists it sent: per
        kind (``COMMANDED``) the ratio to its limit of every twist sent (``sent``). The TCP's linear and
        angular speed; every joint's share of its speed limit, through the differential IK where the arm
        was when the twist was sent; and, as finite differences over the control period of the twists sent
        one period after another from rest (a stream starts at rest, after a stop or a trajectory too), the
        TCP's linear and angular acceleration and jerk."""
        sf = self.cfg.safety
        v = np.array(self.sent) if self.sent else np.zeros((0, 6))
        qd_limit = self.model.qd_max * sf.joint_velocity_scale
        out = {"tcp_linear_speed": np.linalg.norm(v[:, :3], axis=1) / sf.tcp_max_linear_mps,
               "tcp_angular_speed": np.linalg.norm(v[:, 3:], axis=1) / sf.tcp_max_angular_rps,
               "joint_velocity_share": np.array([np.max(np.abs(self.model.velocity_map(q)(vk)) / qd_limit)
                                                 for vk, (_, q) in zip(v, self.sent_at, strict=True)])}
        t = np.array([at[0] for at in self.sent_at])
        # Runs of twists sent in consecutive periods, each preceded by rest.
        runs = np.split(v, np.flatnonzero(np.abs(np.diff(t) - self.dt) > 1e-9) + 1)
        rates = ((1, "acceleration", sf.tcp_max_linear_acc_mps2, sf.tcp_max_angular_acc_rps2),
                 (2, "jerk", sf.tcp_max_linear_jerk_mps3, sf.tcp_max_angular_jerk_rps3))
        for k, what, linear, angular in rates:
            x = np.vstack([np.diff(np.vstack([np.zeros((k, 6)), run]), n=k, axis=0) / self.dt ** k
                           for run in runs]) if len(v) else np.zeros((0, 6))
            out[f"tcp_linear_{what}"] = np.linalg.norm(x[:, :3], axis=1) / linear
            out[f"tcp_angular_{what}"] = np.linalg.norm(x[:, 3:], axis=1) / angular
        return out

    def check_sent(self) -> None:
        """Every twist sent keeps each streaming limit of the cell file (:meth:`commanded`) within
        rounding; a speed, up to ``SPEED_SLACK`` over while the jerk limit slows it down."""
        for kind, ratio in self.commanded().items():
            allowed = 1.0 + 1e-6 + (SPEED_SLACK if kind in COMMANDED_SPEEDS else 0.0)
            worst = float(np.max(ratio, initial=0.0))
            assert worst <= allowed, f"a streamed twist's {kind}: {worst:.4g} times the limit"


def _frame_along(a: Array, b: Array) -> Array:
    """A pose centred between ``a`` and ``b`` whose z axis points from ``a`` to ``b`` (FCL's capsules lie
    along z)."""
    z = (b - a) / np.linalg.norm(b - a)
    other = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = np.cross(other, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = (a + b) / 2.0
    return T


def _max_ratio(values: Array, limits: Array | float) -> float:
    """Largest |value| / limit."""
    return float(np.max(np.abs(values) / limits))


PHASES = {ArmMode.VELOCITY: "streamed", ArmMode.TRAJECTORY: "trajectory", ArmMode.STOPPING: "braking",
          ArmMode.FAULT: "braking", ArmMode.IDLE: "idle"}
BREACHES = ("barrier_crossing", "collision", "joint_limit", "joint_velocity", "joint_acceleration",
            "joint_jerk")
"""What must never happen, each counted in samples (control periods)."""
COMMANDED_SPEEDS = ("tcp_linear_speed", "tcp_angular_speed", "joint_velocity_share")
COMMANDED = (*COMMANDED_SPEEDS, "tcp_linear_acceleration", "tcp_angular_acceleration", "tcp_linear_jerk",
             "tcp_angular_jerk")
"""The streaming limits of the cell file, judged on the twists the guard sends (``Rig.commanded``)."""
CELL_LIMITS = ("barrier_margin", "joint_margin", "joint_velocity_share", "tcp_linear_speed",
               "tcp_angular_speed", "tcp_linear_acceleration", "tcp_angular_acceleration", "tcp_linear_jerk",
               "tcp_angular_jerk", "joint_acceleration_share", "joint_jerk_share")
"""The tighter limits of the cell file that the guard aims to keep, each counted in samples over it."""


class MotionJudge:
    """Judges an arm's realized motion, sample by sample (see the module docstring).

    ``breaches`` counts samples where something happened that must never happen: a guarded point (the
    flange origin or the sensor origin) past a barrier plane of the cell file or a face of its workspace
    box; a link capsule or tool body touching the table, the object's box (as given, not inflated), an
    obstacle, or a moving body not adjacent to it; a joint at its limit; a joint faster, or accelerating
    or jerking harder, than the robot model's maxima (jerk is not judged while the arm brakes by itself,
    which it does at full deceleration at once).

    ``cell_limits`` counts samples over the cell file's own, tighter limits: a guarded point inside the
    barrier margin, a joint inside its position margin, joint speed above the cell's share of its
    maximum; for streamed motion the flange's speed, acceleration and jerk above the TCP limits (what the
    guard's clamps and smoothing bound); for a trajectory the flange's speed (with the guard's allowance
    of 2 %) and the joints' acceleration and jerk above the cell's shares of their maxima (what ruckig
    plans to). ``worst`` holds the worst value of every kind: a depth [m or rad] for barriers and joint
    positions, a ratio to the limit for rates.
    """

    def __init__(self, cfg: CellConfig, model: RobotModel, dt: float) -> None:
        s = cfg.safety
        self._model = model
        self._dt = dt
        self._T_fs = cfg.mount.matrix()
        self._plane_points = np.array([p.point for p in s.barrier_planes], dtype=float).reshape(-1, 3)
        normals = np.array([p.normal for p in s.barrier_planes], dtype=float).reshape(-1, 3)
        self._plane_normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        self._box = (np.asarray(s.workspace.min_m, dtype=float), np.asarray(s.workspace.max_m, dtype=float))
        self._margin_m = s.barrier_margin_m
        self._margin_rad = s.joint_position_margin_rad
        self._shares = (s.joint_velocity_scale, s.joint_acceleration_scale, s.joint_jerk_scale)
        self._tcp = ((s.tcp_max_linear_mps, s.tcp_max_angular_rps),
                     (s.tcp_max_linear_acc_mps2, s.tcp_max_angular_acc_rps2),
                     (s.tcp_max_linear_jerk_mps3, s.tcp_max_angular_jerk_rps3))
        self._build_bodies(cfg)
        self.breaches: Counter[str] = Counter(dict.fromkeys(BREACHES, 0))
        self.cell_limits: Counter[str] = Counter(dict.fromkeys(CELL_LIMITS, 0))
        self.worst: dict[str, float] = {}
        self.first_contact: str | None = None
        self.start(model.q_home)

    # ------------------------------------------------------------------ bodies

    def _build_bodies(self, cfg: CellConfig) -> None:
        m = self._model
        specs = m.capsule_specs
        lengths = [float(np.linalg.norm(np.subtract(c.b, c.a))) for c in specs]
        self._names = [c.name for c in specs]
        self._moving = [fcl.CollisionObject(fcl.Capsule(c.radius, h)) for c, h in zip(specs, lengths,
                                                                                      strict=True)]
        local = [_frame_along(np.asarray(c.a, dtype=float), np.asarray(c.b, dtype=float)) for c in specs]
        radii = [c.radius + h / 2.0 for c, h in zip(specs, lengths, strict=True)]
        frames = [c.frame for c in specs]
        for body in cfg.safety.collision.tool:
            if body.shape != "box":
                raise ValueError(f"the judge models box tools, not {body.shape}")
            self._names.append(body.name)
            self._moving.append(fcl.CollisionObject(fcl.Box(*body.size_m)))
            local.append(body.pose.matrix())
            radii.append(float(np.linalg.norm(body.size_m)) / 2.0)
            frames.append(m.n_joints + 1)  # fk_all's last frame: the flange
        self._local = np.array(local)
        self._frames = np.array(frames)
        self._radii = np.array(radii)
        # Two capsules touch by construction where the model says so; the tool sits on the flange and
        # touches the capsules on the flange's frame and on the one before it (fk_all's flange is the last
        # link's frame on an arm without a flange element).
        flange_frame = m.n_joints + (0 if m.flange is None else 1)
        wrist = {c.name for c in specs if c.frame >= flange_frame - 1}
        n_caps = len(specs)
        pairs = [(i, j) for i in range(len(self._moving)) for j in range(i + 1, len(self._moving))
                 if (j < n_caps and not m.are_adjacent(self._names[i], self._names[j]))
                 or (j >= n_caps and (i >= n_caps or self._names[i] not in wrist))]
        self._pairs = np.array(pairs, dtype=int).reshape(-1, 2)
        self._standing = self._frames == 0  # the base stands on the table
        table = cfg.safety.collision.table
        slab = np.eye(4)
        slab[:3, 3] = [*table.center_xy_m, cfg.station.table_z_m - table.thickness_m / 2.0]
        self._statics: list[tuple[str, fcl.CollisionObject, Array, float]] = []
        self._add_box("table", np.array([*table.size_m, table.thickness_m]), slab)
        for ob in cfg.safety.collision.obstacles:
            if ob.shape != "box":
                raise ValueError(f"the judge models box obstacles, not {ob.shape}")
            self._add_box(ob.name, np.asarray(ob.size_m, dtype=float), ob.pose.matrix())
        self._n_fixed = len(self._statics)
        self._request = fcl.CollisionRequest()

    def _add_box(self, name: str, size: Array, T: Array) -> None:
        obj = fcl.CollisionObject(fcl.Box(*size), fcl.Transform(T[:3, :3], T[:3, 3]))
        self._statics.append((name, obj, T[:3, 3].copy(), float(np.linalg.norm(size)) / 2.0))

    def set_roi(self, aabb_min: Array | None, aabb_max: Array | None) -> None:
        """The object's box (base frame [m]) as it is, without a margin; None removes it."""
        del self._statics[self._n_fixed:]
        if aabb_min is None or aabb_max is None:
            return
        lo, hi = np.asarray(aabb_min, dtype=float), np.asarray(aabb_max, dtype=float)
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2.0
        self._add_box("object", hi - lo, T)

    def contact(self, q: Array, frames: Array | None = None) -> str | None:
        """The first two bodies in contact at joints ``q`` [rad], in words, or None; ``frames``: the
        model's ``fk_all(q)`` when already known."""
        F = self._model.fk_all(q) if frames is None else frames
        T = F[self._frames] @ self._local
        for obj, Tk in zip(self._moving, T, strict=True):
            obj.setTransform(fcl.Transform(Tk[:3, :3], Tk[:3, 3]))
        centres = T[:, :3, 3]
        for k, (name, obj, centre, radius) in enumerate(self._statics):
            near = np.linalg.norm(centres - centre, axis=1) <= self._radii + radius
            if k == 0:
                near &= ~self._standing
            for i in np.flatnonzero(near):
                if fcl.collide(self._moving[i], obj, self._request, fcl.CollisionResult()):
                    return f"{self._names[i]} touches {name}"
        ia, ib = self._pairs[:, 0], self._pairs[:, 1]
        near = np.linalg.norm(centres[ia] - centres[ib], axis=1) <= self._radii[ia] + self._radii[ib]
        for i, j in self._pairs[near]:
            if fcl.collide(self._moving[i], self._moving[j], self._request, fcl.CollisionResult()):
                return f"{self._names[i]} touches {self._names[j]}"
        return None

    def guarded_points(self, T_base_flange: Array) -> Array:
        """The flange origin and the sensor origin (2, 3) [m] in the base frame."""
        return np.array([T_base_flange[:3, 3], (T_base_flange @ self._T_fs)[:3, 3]])

    def clearance(self, q: Array) -> float:
        """The smallest signed distance [m] of a guarded point at joints ``q`` to a barrier plane or a
        workspace face (negative: crossed)."""
        return self._clearance(self.guarded_points(self._model.fk(q)))

    def _clearance(self, p: Array) -> float:
        d = np.einsum("kpj,pj->kp", p[:, None, :] - self._plane_points[None], self._plane_normals)
        lo, hi = self._box
        return float(min(np.min(d, initial=np.inf), np.min(p - lo), np.min(hi - p)))

    # ------------------------------------------------------------------ judging

    def start(self, q: Array) -> None:
        """Begin a record with the arm at rest at joints ``q`` [rad]."""
        q = np.array(q, dtype=float)
        T = self._model.fk(q)
        self._q = [q] * 4
        self._p = [T[:3, 3].copy()] * 4
        self._R = T[:3, :3].copy()
        self._w = [np.zeros(3)] * 3
        self._phases = ["idle"] * 3

    def _judge(self, counter: Counter[str], kind: str, value: float, over: float) -> None:
        """Keep the worst ``value`` of ``kind``; count it in ``counter`` when it is above ``over``."""
        self.worst[kind] = max(self.worst.get(kind, -np.inf), value)
        counter[kind] += value > over

    def observe(self, q: Array, mode: ArmMode) -> None:
        """The joints [rad] the arm reached after one control period spent in ``mode``."""
        m, dt, B, C = self._model, self._dt, self.breaches, self.cell_limits
        q = np.array(q, dtype=float)
        F = m.fk_all(q)
        T = F[-1]
        self._q = [*self._q[1:], q]
        self._p = [*self._p[1:], T[:3, 3].copy()]
        self._w = [*self._w[1:], rotvec(T[:3, :3] @ self._R.T) / dt]
        self._R = T[:3, :3].copy()
        self._phases = [*self._phases[1:], PHASES[mode]]
        phase, window = self._phases[-1], set(self._phases)

        clearance = self._clearance(self.guarded_points(T))
        self._judge(B, "barrier_crossing", -clearance, 0.0)
        self._judge(C, "barrier_margin", self._margin_m - clearance, 0.0)
        hit = self.contact(q, F)
        B["collision"] += hit is not None
        if hit is not None and self.first_contact is None:
            self.first_contact = hit
        depth = float(np.max(np.maximum(m.q_min - q, q - m.q_max)))
        self._judge(B, "joint_limit", depth, -AT_LIMIT_RAD)
        self._judge(C, "joint_margin", depth + self._margin_rad, 0.0)

        qd = np.diff(np.array(self._q), axis=0) / dt  # the last three steps
        qdd = np.diff(qd, axis=0) / dt
        qddd = (qdd[1] - qdd[0]) / dt
        over = 1.0 + RATE_SLACK
        self._judge(B, "joint_velocity", _max_ratio(qd[-1], m.qd_max), over)
        self._judge(B, "joint_acceleration", _max_ratio(qdd[-1], m.qdd_max), over)
        if "braking" not in window:
            self._judge(B, "joint_jerk", _max_ratio(qddd, m.qddd_max), over)
        vel_share, acc_share, jerk_share = self._shares
        self._judge(C, "joint_velocity_share", _max_ratio(qd[-1], m.qd_max * vel_share), over)

        v = np.diff(np.array(self._p), axis=0) / dt
        w = np.array(self._w)
        lin = (v[-1], (v[-1] - v[-2]) / dt, (v[-1] - 2.0 * v[-2] + v[-3]) / dt**2)
        ang = (w[-1], (w[-1] - w[-2]) / dt, (w[-1] - 2.0 * w[-2] + w[-3]) / dt**2)
        if phase in ("streamed", "trajectory"):
            allowance = 1.0 if phase == "streamed" else TRAJECTORY_SPEED_ALLOWANCE
            for name, x, limit in (("linear", lin[0], self._tcp[0][0]), ("angular", ang[0], self._tcp[0][1])):
                self._judge(C, f"tcp_{name}_speed", float(np.linalg.norm(x)) / (limit * allowance), over)
        if window <= {"streamed", "idle"} and phase == "streamed":
            for k, what in ((1, "acceleration"), (2, "jerk")):
                for name, x, limit in (("linear", lin[k], self._tcp[k][0]),
                                       ("angular", ang[k], self._tcp[k][1])):
                    self._judge(C, f"tcp_{name}_{what}", float(np.linalg.norm(x)) / limit, over)
        if window <= {"trajectory", "idle"} and phase == "trajectory":
            self._judge(C, "joint_acceleration_share", _max_ratio(qdd[-1], m.qdd_max * acc_share), over)
            self._judge(C, "joint_jerk_share", _max_ratio(qddd, m.qddd_max * jerk_share), over)
