"""Safety soak: random streamed twists and point-to-point moves, per robot, through the real motion guard
(``cell.safety.guard``) and the simulated arm, every control period of the motion judged by
``tests.safety_rig.MotionJudge``, which shares no code with the guard.

Each episode builds a cell from the robot's sim cell file the way a job builds it (``tests.safety_rig.Rig``)
with a random start configuration (collision-free, inside the joint margins, 1 cm clear of the barrier
margins; in a third of them one joint 2 mrad to 0.25 rad from its margin), one to three random barrier
planes 7 mm to 25 cm from the TCP or the sensor, a random object box (3 to 25 cm on a side, 10 to 45 cm
from the flange) as the guard's ROI and, in half of the episodes, another such box as an obstacle in the
cell file. It then sends ``COMMANDS_PER_EPISODE`` random commands:

- twists (92 %): towards one of the episode's planes, towards the object, or anywhere; up to twice the
  cell's speed limits; held for 1 to 4 control periods (80 %) or 8 to 30;
- holds (5 %): the streamed twist ramped down, for 5 to 20 control periods;
- moves (3 %): streaming ends, the arm comes to rest and a ruckig trajectory to a random joint goal (within
  0.3 rad of the joints or, one time in three, 1.2 rad; clipped to the joint limits, so some lie inside
  the margin) is checked by the guard and, unless refused, followed to its end.

A refusal stops the arm: it is counted, the arm comes to rest and the episode goes on.

Prints one line per robot and then one line of JSON: per robot the commands sent, those refused (by
reason), ``breaches`` (control periods in which something happened that must never happen: a barrier
plane crossed, bodies in contact, a joint at its limit or beyond the robot model's speed, acceleration or
jerk; each must be 0), ``cell_limits`` (control periods over the cell file's tighter limits: margins,
limit shares, TCP limits), the worst value of each kind (a depth [m or rad] or a ratio to the limit),
``commanded`` (streamed twists the guard sent over a streaming limit of the cell file as the guard defines
it: TCP speed, acceleration and jerk as differences of the twists sent, each joint's share of its speed
through the differential IK where the arm was; ``Rig.commanded``; each must be 0 but for a speed up to
``SPEED_SLACK`` over while the jerk limit slows it down) with ``worst_commanded``, and ``breach_events``:
the first breaches with the episode and command they came in (``--episodes E:E+1`` replays episode E
alone: the episodes before it are drawn, not run, so it gets the same commands).

``cell_limits`` judges the motion the arm made, not the commands: near a singularity the arm realizes a
twist through damped least squares, short of it by up to half (its flange's speed, acceleration and jerk
are those of ``J(q) DLS(q) v``, whose factor turns with q), so its TCP acceleration and jerk there may pass
the limits by some tens of percent with every command within them (seed 0, 3000 commands: 1.27 on the
UR5e, at a smallest singular value of 5 mm); and a trajectory slowed down in time (``trajectory_time_scaled``)
has samples off the control period, which the arm joins by straight lines, so its joints' jerk over a
period passes the share the samples keep (1.27 of the UR5e's share in the soak; in 17 random slowed-down
UR5e moves, 0.95 to 1.44 over a period where their samples keep 0.03 to 0.41 of it).

    .venv/bin/python benchmarks/safety_soak.py [--commands N] [--seed S] [--robot ur5e|panda ...]
    .venv/bin/python benchmarks/safety_soak.py --robot ur5e --seed S --episodes 121:122   # replay one
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from options import BenchmarkParser, at_least, count, first_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.control.trajectory import joint_trajectory
from cell.safety.guard import SPEED_SLACK, TwistRefused
from drivers.errors import SafetyStop
from drivers.robots import get_robot_model
from tests.safety_rig import COMMANDED, COMMANDED_SPEEDS, MotionJudge, Rig, cell_config

Array = np.ndarray
ROBOTS = ("ur5e", "panda")
COMMANDS_PER_EPISODE = 200
# The first breaches are listed with where they happened (episode, command), so that one can be replayed.
MAX_BREACH_EVENTS = 50
START_TRIES = 10_000
BOX_TRIES = 50
# Random boxes keep this far [m] from the arm at the start: more than the ROI margin the guard inflates by.
BOX_CLEARANCE_M = 0.04


def _unit(rng: np.random.Generator) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


class Episode:
    """A random cell (start joints, planes, object box, obstacle) with its rig; see the module docstring."""

    def __init__(self, robot: str, rng: np.random.Generator, probe: MotionJudge) -> None:
        cfg = cell_config(robot)
        q0 = self._start(cfg.safety.joint_position_margin_rad, cfg.safety.barrier_margin_m, robot, rng, probe)
        points = probe.guarded_points(get_robot_model(robot).fk(q0))
        self.normals = [_unit(rng) for _ in range(int(rng.integers(1, 4)))]
        planes = [{"name": f"random {i}", "normal": n.tolist(),
                   "point": (points[int(np.argmin(points @ n))]
                             - rng.uniform(cfg.safety.barrier_margin_m + 0.002, 0.25) * n).tolist()}
                  for i, n in enumerate(self.normals)]
        self.roi = self._free_box(q0, points[0], rng, probe)
        obstacle = self._free_box(q0, points[0], rng, probe) if rng.random() < 0.5 else None
        obstacles = [] if obstacle is None else [{
            "shape": "box", "name": "random obstacle", "size_m": (obstacle[1] - obstacle[0]).tolist(),
            "pose": {"xyz_m": ((obstacle[0] + obstacle[1]) / 2.0).tolist()}}]
        probe.set_roi(None, None)
        self.rig = Rig(cell_config(robot, home_joints_rad=q0, barrier_planes=planes, obstacles=obstacles))
        if self.roi is not None:
            self.rig.set_roi(*self.roi)

    @staticmethod
    def _start(margin_rad: float, margin_m: float, robot: str, rng: np.random.Generator,
               probe: MotionJudge) -> Array:
        """Joints inside the margins, collision-free, the guarded points 1 cm clear of the barrier margin;
        a third with one joint close to its margin."""
        m = get_robot_model(robot)
        lo, hi = m.q_min + margin_rad, m.q_max - margin_rad
        for _ in range(START_TRIES):
            q = rng.uniform(lo + 0.02, hi - 0.02)
            if rng.random() < 1.0 / 3.0:
                j = int(rng.integers(m.n_joints))
                gap = rng.uniform(0.002, 0.25)
                q[j] = lo[j] + gap if rng.random() < 0.5 else hi[j] - gap
            if probe.contact(q) is None and probe.clearance(q) > margin_m + 0.01:
                return q
        raise RuntimeError(f"no start configuration found for the {robot} in {START_TRIES} tries")

    @staticmethod
    def _free_box(q0: Array, near: Array, rng: np.random.Generator, probe: MotionJudge
                  ) -> tuple[Array, Array] | None:
        """A box 3 to 25 cm on a side, centred 10 to 45 cm from ``near``, clear of the arm at ``q0``."""
        for _ in range(BOX_TRIES):
            size = rng.uniform(0.03, 0.25, size=3)
            centre = near + _unit(rng) * rng.uniform(0.1, 0.45)
            lo, hi = centre - size / 2.0, centre + size / 2.0
            probe.set_roi(lo - BOX_CLEARANCE_M, hi + BOX_CLEARANCE_M)
            if probe.contact(q0) is None:
                return lo, hi
        return None

    def command(self, rng: np.random.Generator, sent: Counter[str], refused: Counter[str]
                ) -> tuple[str, Callable[[], None]]:
        """Draw a random command (see the module docstring): its kind and what runs it. Every random number
        of a command is drawn here, whatever the arm does when it runs, so that the commands of an episode
        can be drawn without running them (``--episodes``)."""
        rig = self.rig
        r = rng.random()
        if r < 0.03:
            reach = 0.3 if rng.random() < 2.0 / 3.0 else 1.2
            offset = rng.uniform(-reach, reach, rig.model.n_joints)
            return "move", lambda: self.move(offset, sent, refused)
        if r < 0.08:
            ticks = int(rng.integers(5, 21))
            return "hold", lambda: self.hold(ticks, sent)
        twist = self.twist(rng)
        ticks = int(rng.integers(1, 5)) if rng.random() < 0.8 else int(rng.integers(8, 31))

        def stream() -> None:
            sent["twists"] += 1
            rig.guard.command_twist(twist())
            rig.tick(ticks)

        return "twist", stream

    def twist(self, rng: np.random.Generator) -> Callable[[], Array]:
        """A random twist: towards a plane, the object (from where the arm is when it is sent) or anywhere, up
        to twice the speed limits."""
        rig = self.rig
        sf = rig.cfg.safety
        r = rng.random()
        towards_object = 0.35 <= r < 0.6 and self.roi is not None
        if r < 0.35:
            d = -self.normals[int(rng.integers(len(self.normals)))] + 0.3 * _unit(rng)
        elif not towards_object:
            d = _unit(rng)
        speed = rng.uniform(0.0, 2.0 * sf.tcp_max_linear_mps)
        turn = rng.uniform(0.0, 2.0 * sf.tcp_max_angular_rps) if rng.random() < 0.5 else 0.0
        ang = _unit(rng) * turn

        def aim() -> Array:
            way = ((self.roi[0] + self.roi[1]) / 2.0 - rig.arm.state().T_base_flange[:3, 3]
                   if towards_object and self.roi is not None else d)
            return np.concatenate([way / np.linalg.norm(way) * speed, ang])

        return aim

    def hold(self, ticks: int, sent: Counter[str]) -> None:
        """Ramp the streamed twist down and keep still for ``ticks`` control periods."""
        sent["holds"] += 1
        self.rig.guard.hold()
        self.rig.tick(ticks)

    def move(self, offset: Array, sent: Counter[str], refused: Counter[str]) -> None:
        """End streaming, let the arm come to rest, then a ruckig move by ``offset`` [rad] (clipped to the
        joint limits) unless refused."""
        rig, guard, m = self.rig, self.rig.guard, self.rig.model
        sf = rig.cfg.safety
        sent["moves"] += 1
        guard.finish()
        rig.settle()
        q = rig.arm.state().q
        goal = np.clip(q + offset, m.q_min, m.q_max)
        traj = joint_trajectory(m, q, goal, dt=rig.dt, velocity_scale=sf.joint_velocity_scale,
                                acceleration_scale=sf.joint_acceleration_scale,
                                jerk_scale=sf.joint_jerk_scale)
        _, refusal = guard.check_trajectory(traj)
        if refusal is not None:
            refused[f"move: {refusal.kind}"] += 1
            return
        guard.execute_trajectory(traj)
        rig.tick()
        while guard.following:
            rig.tick()


def soak(robot: str, n_commands: int, seed: int, first_episode: int = 0) -> dict[str, Any]:
    """Run ``n_commands`` random commands on ``robot`` (see the module docstring), from episode
    ``first_episode`` of the seed's sequence on (the earlier ones are drawn, not run); returns its
    figures."""
    rng = np.random.default_rng(seed)
    probe_cfg = cell_config(robot)
    probe = MotionJudge(probe_cfg, get_robot_model(robot), 1.0 / probe_cfg.scan.control_rate_hz)
    # every kind counted from 0, so that a soak too short for a move still reports 0 moves
    sent: Counter[str] = Counter(dict.fromkeys(("commands", "episodes", "twists", "holds", "moves"), 0))
    refused: Counter[str] = Counter()
    breaches: Counter[str] = Counter()
    cell_limits: Counter[str] = Counter()
    commanded: Counter[str] = Counter(dict.fromkeys(COMMANDED, 0))
    worst: dict[str, float] = {}
    worst_commanded: dict[str, float] = {}
    contacts: Counter[str] = Counter()
    events: list[dict[str, Any]] = []
    periods = 0
    t0 = time.perf_counter()
    for _ in range(first_episode):
        skipped = Episode(robot, rng, probe)
        for _ in range(COMMANDS_PER_EPISODE):
            skipped.command(rng, sent, refused)
    number = first_episode
    while sent["commands"] < n_commands:
        episode = Episode(robot, rng, probe)
        rig = episode.rig
        sent["episodes"] += 1
        for index in range(min(COMMANDS_PER_EPISODE, n_commands - sent["commands"])):
            sent["commands"] += 1
            before = sum(rig.judge.breaches.values())
            kind, run = episode.command(rng, sent, refused)
            try:
                run()
            except TwistRefused as exc:
                refused[f"twist: {exc.refusal.kind}"] += 1
                rig.settle()
            except SafetyStop as exc:
                refused[f"stop: {exc.reason.split(':')[0]}"] += 1
                rig.settle()
            if sum(rig.judge.breaches.values()) > before and len(events) < MAX_BREACH_EVENTS:
                events.append({"episode": number, "command": index, "command_kind": kind,
                               "breaches": {k: v for k, v in rig.judge.breaches.items() if v},
                               "first_contact": rig.judge.first_contact})
        rig.guard.finish()
        rig.settle()
        judge = rig.judge
        breaches.update(judge.breaches)
        cell_limits.update(judge.cell_limits)
        if judge.first_contact is not None:
            contacts[judge.first_contact] += 1
        for kind, value in judge.worst.items():
            worst[kind] = max(worst.get(kind, -np.inf), value)
        for kind, ratio in rig.commanded().items():
            allowed = 1.0 + 1e-6 + (SPEED_SLACK if kind in COMMANDED_SPEEDS else 0.0)
            commanded[kind] += int(np.count_nonzero(ratio > allowed))
            worst_commanded[kind] = max(worst_commanded.get(kind, 0.0), float(np.max(ratio, initial=0.0)))
        periods += round(rig.clock.now() / rig.dt)
        number += 1
    return {"robot": robot, "seed": seed, **sent, "control_periods": periods,
            "sim_time_h": round(periods * rig.dt / 3600.0, 2),
            "refused_total": sum(refused.values()), "refused": dict(sorted(refused.items())),
            "breaches_total": sum(breaches.values()), "breaches": dict(breaches),
            "first_contacts": dict(contacts), "cell_limits": dict(cell_limits),
            "worst": {k: float(f"{v:.4g}") for k, v in worst.items()},
            "commanded": dict(commanded),
            "worst_commanded": {k: float(f"{v:.4g}") for k, v in worst_commanded.items()},
            "breach_events": events,
            "wall_s": round(time.perf_counter() - t0, 1)}


def _episodes(text: str) -> tuple[int, int]:
    """``FROM:TO`` as two episode numbers, 0 <= FROM < TO."""
    first, _, last = text.partition(":")
    try:
        bounds = int(first), int(last)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected FROM:TO (two episode numbers), got {text!r}") from None
    if not 0 <= bounds[0] < bounds[1]:
        raise argparse.ArgumentTypeError(f"expected 0 <= FROM < TO, got {text!r}")
    return bounds


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--commands", type=count, default=100_000, help="random commands per robot")
    parser.add_argument("--seed", type=at_least(0), default=0, help="seed of the random generator")
    parser.add_argument("--episodes", metavar="FROM:TO", type=_episodes, help="run only episodes FROM to "
                        "TO - 1 of the seed's sequence (e.g. one that ``breach_events`` names), in place of "
                        "--commands")
    parser.add_argument("--robot", choices=ROBOTS, action="append", help="robot to soak (repeatable; "
                        "default: both)")
    args = parser.parse_args()
    results = []
    for robot in args.robot or ROBOTS:
        first, last = args.episodes or (0, None)
        n_commands = args.commands if last is None else (last - first) * COMMANDS_PER_EPISODE
        r = soak(robot, n_commands, args.seed, first)
        results.append(r)
        print(f"{robot:6s} {r['commands']} commands ({r['twists']} twists, {r['holds']} holds, {r['moves']} "
              f"moves) over {r['sim_time_h']} h of sim time: {r['refused_total']} refused, "
              f"{r['breaches_total']} breaches, {sum(r['commanded'].values())} commands over a limit, "
              f"{r['wall_s']} s", flush=True)
    print(json.dumps({"robots": results, "breaches_total": sum(r["breaches_total"] for r in results)}))


if __name__ == "__main__":
    main()
