"""How fast the inverse kinematics solves a pose, with the closed-form rotation helpers of
``drivers.transforms`` against SciPy's compiled ``Rotation`` (what they replaced) as the reference.

``RobotModel.ik_pose`` iterates damped least-squares steps, each on the pose error whose rotation part
is an axis-angle vector (``drivers.transforms.pose_error``). The reference runs the same solves with that
axis-angle taken from ``Rotation.from_matrix(R).as_rotvec()``. Per model (UR5e, Panda), ``--goals`` goal
poses are the flange at random joints within the limits, each solved from the home joints; a repeat times
all of them once with each implementation, in turn (closed form, reference, closed form, ...), and the
medians over ``--repeats`` repeats are compared. The per-call cost of the primitives (axis-angle and
quaternion of one matrix, the matrix of one axis-angle) is timed the same way. The solves' joints agree
(the two give the same error to 1e-15 rad, ``tests/test_transforms.py``).

Prints readable lines, then as its last line JSON {"ik_ms": {model: {"closed_form": ms per solve,
"scipy": ms, "ratio": closed / scipy}}, "primitive_us": {name: {"closed_form": us, "scipy": us,
"ratio": ...}}}.

    .venv/bin/python benchmarks/ik_solve.py [--goals 40] [--repeats 5]
"""

from __future__ import annotations

import contextlib
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from options import BenchmarkParser, count, first_paragraph
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import drivers.robots.model as model_module
from drivers.errors import KinematicsError
from drivers.robots import get_robot_model
from drivers.transforms import pose_error, quat_xyzw, rotation_from_rotvec, rotvec

PRIMITIVE_CALLS = 2000


def scipy_pose_error(T_current: np.ndarray, T_goal: np.ndarray) -> np.ndarray:
    """``pose_error`` with its axis-angle from SciPy's ``Rotation`` (the reference)."""
    dr = Rotation.from_matrix(T_goal[:3, :3] @ T_current[:3, :3].T).as_rotvec()
    return np.concatenate([T_goal[:3, 3] - T_current[:3, 3], dr])


def solve_all(name: str, goals: list[np.ndarray], error: Callable[..., np.ndarray]) -> float:
    """Wall time [ms] per solve of every goal from home, with ``error`` as the IK's pose error."""
    model = get_robot_model(name)
    model_module.pose_error = error
    try:
        start = time.perf_counter()
        for T in goals:
            # a goal the DLS does not reach from home costs its 200 iterations in both
            with contextlib.suppress(KinematicsError):
                model.ik_pose(T, model.q_home)
        return (time.perf_counter() - start) * 1e3 / len(goals)
    finally:
        model_module.pose_error = pose_error


def per_call_us(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    for _ in range(PRIMITIVE_CALLS):
        fn()
    return (time.perf_counter() - start) * 1e6 / PRIMITIVE_CALLS


def compared(closed: list[float], reference: list[float]) -> dict[str, float]:
    c, r = statistics.median(closed), statistics.median(reference)
    return {"closed_form": round(c, 3), "scipy": round(r, 3), "ratio": round(c / r, 3)}


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--goals", type=count, default=40)
    parser.add_argument("--repeats", type=count, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    goals = {}
    for name in ("ur5e", "panda"):
        model = get_robot_model(name)
        goals[name] = [model.fk(rng.uniform(model.q_min, model.q_max)) for _ in range(args.goals)]
    R = Rotation.random(random_state=1).as_matrix()
    r = Rotation.from_matrix(R).as_rotvec()
    primitives: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {
        "axis_angle_of_matrix": (lambda: rotvec(R), lambda: Rotation.from_matrix(R).as_rotvec()),
        "quaternion_of_matrix": (lambda: quat_xyzw(R), lambda: Rotation.from_matrix(R).as_quat()),
        "matrix_of_axis_angle": (lambda: rotation_from_rotvec(r),
                                 lambda: Rotation.from_rotvec(r).as_matrix()),
    }
    ik: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in goals}
    calls: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in primitives}
    for repeat in range(args.repeats):
        for name, poses in goals.items():
            ik[name][0].append(solve_all(name, poses, pose_error))
            ik[name][1].append(solve_all(name, poses, scipy_pose_error))
            print(f"repeat {repeat}: {name} {ik[name][0][-1]:.2f} ms per solve (closed form), "
                  f"{ik[name][1][-1]:.2f} ms (SciPy)", flush=True)
        for name, (closed, reference) in primitives.items():
            calls[name][0].append(per_call_us(closed))
            calls[name][1].append(per_call_us(reference))
    report = {"ik_ms": {name: compared(*times) for name, times in ik.items()},
              "primitive_us": {name: compared(*times) for name, times in calls.items()}}
    for name, figures in report["ik_ms"].items():
        print(f"{name}: {figures['closed_form']} ms per IK solve, SciPy {figures['scipy']} ms, "
              f"ratio {figures['ratio']}")
    for name, figures in report["primitive_us"].items():
        print(f"{name}: {figures['closed_form']} us, SciPy {figures['scipy']} us, ratio {figures['ratio']}")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
