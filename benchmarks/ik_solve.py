"""How fast the inverse kinematics solves a pose, with the closed-form rotation helpers of
``drivers.transforms`` against SciPy's compiled ``Rotation`` (what they replaced) as the reference.

``RobotModel.ik_pose`` iterates damped least-squares steps, each on the pose error whose rotation part
is an axis-angle vector (``drivers.transforms.pose_error``). The reference runs the same solves with that
axis-angle taken from ``Rotation.from_matrix(R).as_rotvec()``. Per model (UR5e, Panda), ``--goals`` goal
poses are the flange at random joints within the limits, each solved from the home joints. After one
untimed warm-up of each (imports, first-call caches), a repeat times all of them once with each
implementation, in turn, the one that runs first alternating from repeat to repeat
(``benchmarks/interleaved.py``): the figures are the medians over ``--repeats`` repeats, the ratio the
median of the repeats' own ratios (closed form / SciPy of one repeat), their range beside. The per-call
cost of the primitives (axis-angle and quaternion of one matrix, the matrix of one axis-angle) is timed
the same way. The solves' joints agree (the two give the
same error to 1e-15 rad, ``tests/test_transforms.py``).

Prints readable lines, then as its last line JSON {"ik_ms": {model: {"closed_form": ms per solve,
"scipy": ms, "ratio": the median of the repeats' closed / scipy, "ratio_range": [min, max] over the
repeats}}, "primitive_us": {name: {"closed_form": us, "scipy": us, "ratio": ..., "ratio_range": ...}}}.

    .venv/bin/python benchmarks/ik_solve.py [--goals 40] [--repeats 6]
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from interleaved import Comparison, compared, in_turn
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


def figures(c: Comparison) -> dict[str, float | list[float]]:
    return {"closed_form": round(c.this, 3), "scipy": round(c.reference, 3), **c.ratios()}


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--goals", type=count, default=40)
    parser.add_argument("--repeats", type=count, default=6)
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
    errors = (pose_error, scipy_pose_error)  # closed form, reference: the order of the lists below
    for name, poses in goals.items():  # warm-up, untimed
        for error in errors:
            solve_all(name, poses[:1], error)
    for pair in primitives.values():
        for fn in pair:
            fn()
    ik: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in goals}
    calls: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in primitives}
    for repeat in range(args.repeats):
        for name, poses in goals.items():
            for side in in_turn(repeat, (0, 1)):
                ik[name][side].append(solve_all(name, poses, errors[side]))
            print(f"repeat {repeat}: {name} {ik[name][0][-1]:.2f} ms per solve (closed form), "
                  f"{ik[name][1][-1]:.2f} ms (SciPy)", flush=True)
        for name, pair in primitives.items():
            for side in in_turn(repeat, (0, 1)):
                calls[name][side].append(per_call_us(pair[side]))
    ik_compared = {name: compared(*times) for name, times in ik.items()}
    calls_compared = {name: compared(*times) for name, times in calls.items()}
    for name, c in ik_compared.items():
        print(f"{name}: {c.this:.3f} ms per IK solve, SciPy {c.reference:.3f} ms, {c.text()}")
    for name, c in calls_compared.items():
        print(f"{name}: {c.this:.3f} us, SciPy {c.reference:.3f} us, {c.text()}")
    report = {"ik_ms": {name: figures(c) for name, c in ik_compared.items()},
              "primitive_us": {name: figures(c) for name, c in calls_compared.items()}}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
