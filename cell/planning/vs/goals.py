"""VS-Global (visual-servoing paper section II-D, eq. 10-11): servo towards the best of many sampled views.

Candidates: ``n_candidates`` (5000) camera positions drawn uniformly on the sphere of radius Z* around the
object centroid, each looking at the centroid (image "up" towards +z of the base, as ``look_at``);
those that put the TCP or the sensor outside a barrier plane or the workspace are rejected
(``session.sensor_pose_allowed``). The goal is the argmax of f over the rest (eq. 10), all scored in one
batch, among the candidates the arm can reach: the paper rejects "goal candidates outside the workspace",
and for an arm the workspace is also what its joints reach. Its barrier planes were placed by hand to
keep the Panda clear of its joint limits; for any cell and placement, the candidates are tried in
descending f and the first the arm can servo to is the goal, at most ``reachability_checks`` of them (0:
no check), skipping those within ``arrival_m`` of one that failed (the same goal to the servo: the best
candidates cluster, and 50 checks went to one unreachable cluster). "Can servo to": inverse kinematics
follows the arc of the sphere from the camera to the candidate, in steps of ``path_step_m``, within the
joint margins, free of collision, clear of the edge of the arm's reach (``vs.singular_value_activation``,
which the servo keeps the arm from crossing) and without a change of configuration
(``session.sensor_path_reachable``): g of eq. 11 takes the camera along that arc.
Without a check, a bunny scan spent 20 s at a time pressing towards goals behind the Panda's elbow limit;
with the goal alone checked, goals whose way led the arm into itself (link 0 against link 5) were still
given up after 3 s.

Eq. 11: g = a(r, r*) (x, y, 0, 0, 0, 0), with (x, y) the goal origin expressed in the current camera frame,
normalised: the tangent direction of the shortest path on the sphere, since the camera looks at the
centre. a = min(1, d / ``slow_radius_m``), d the distance between the camera and goal origins [m]: unit
far away, decaying linearly to 0 within 10 cm. Like VS-Local's, the direction is projected into the set
the barrier planes allow. A goal counts as reached within ``arrival_m``; one the camera stops getting
closer to (less than ``stall_progress_m`` nearer than ``stall_time_s`` ago: held by a barrier plane, a
joint limit or a refused direction) is given up; either way a new goal is sampled. Progress is measured
along the sphere (the arc between the camera and the goal about the centroid the goal was sampled
around), the way g moves the camera: the straight-line distance to a goal on the far side shrinks at
only cos(theta / 2) of the camera's speed, theta the angle between them (0.3 for a goal 145 deg away),
and far goals were given up after 3 s at full speed. The paper gives no rule for a goal that cannot be
reached; a fixed time limit instead (20 s) gave up goals on the far side of the object 8 cm before
arrival, the exploration speed of eq. 1 being about 2 cm/s.

The scan ends on the H_ROI rule of eq. 12 (``ServoScanPlanner.entropy_settled``), judged on the values
recorded after the first goal was reached or given up: the paper gives no rule for the way to the first
goal, and a flat H_ROI while travelling there says only that the start view's surroundings are known.

The candidates are drawn from the job's planner generator (``ScanSession.rng``, a stream of the job
seed), so that a scan is repeatable for its seed.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.planning.base import Array, ScanSession
from cell.planning.vs.objective import EntropyObjective, PoseBatch
from cell.planning.vs.servo_scan import Secondary, ServoScanPlanner
from drivers.errors import PlanningError
from drivers.transforms import smallest_rotation


def sphere_views(centre: Array, radius: float, directions: Array) -> PoseBatch:
    """Camera poses (n, 4, 4) at ``centre + radius * directions`` (unit (n, 3)) looking at ``centre``,
    with ``look_at``'s convention (x = z x up, y = z x x, up = +z of the base). Directions along +-z
    have no defined roll; callers draw them with probability zero."""
    z = -np.asarray(directions, dtype=np.float64)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    T = np.zeros((z.shape[0], 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, z
    T[:, :3, 3] = centre - radius * z
    T[:, 3, 3] = 1.0
    return T


def arc_views(centre: Array, radius: float, start: Array, goal: Array, step_m: float) -> PoseBatch:
    """Camera poses (K, 4, 4) along the shorter great-circle arc of the sphere around ``centre`` from the
    direction of the camera pose ``start`` (4, 4) to that of ``goal`` (3,) [m], every ``step_m`` of arc
    [m] or closer, the last at the goal, the first one step away from the start; each looks at
    ``centre`` with the roll about its optical axis carried over from the pose before by the smallest
    rotation, from ``start``'s: the servo turns the camera so (eq. 1 has no rotation about the optical
    axis while the centroid is on it), whatever roll ``sphere_views`` gives the goal candidate. (With the
    candidates' roll the first pose of every arc asked a camera the servo had rolled by 180 deg to turn
    the wrist over at once, and a VS-Hybrid cube scan found none of 116 places reachable.) Antipodal
    points have no shorter arc; the one through the top is taken."""
    a = (start[:3, 3] - centre) / np.linalg.norm(start[:3, 3] - centre)
    b = (goal - centre) / np.linalg.norm(goal - centre)
    angle = angle_between(a, b)
    n = max(1, int(np.ceil(angle * radius / step_m)))
    ortho = b - a * float(a @ b)
    if np.linalg.norm(ortho) < 1e-9:
        ortho = np.array([0.0, 0.0, 1.0]) - a * a[2]
    ortho /= np.linalg.norm(ortho)
    phi = angle * np.arange(1, n + 1) / n
    directions = np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * ortho
    T = np.zeros((n, 4, 4))
    T[:, 3, 3] = 1.0
    # the start's frame, its optical axis aimed at the centre by the smallest rotation
    R = smallest_rotation(start[:3, 2], -a) @ start[:3, :3]
    for k, d in enumerate(directions):
        R = smallest_rotation(R[:, 2], -d) @ R
        T[k, :3, :3] = R
        T[k, :3, 3] = centre + radius * d
    return T


def angle_between(a: Array, b: Array) -> float:
    """The angle [rad] between vectors ``a`` and ``b`` (3,), accurate near 0 and pi."""
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


class GoalSeeker:
    """Eq. 10-11: samples goals and steers towards the current one (module docstring)."""

    def __init__(self, config: CellConfig) -> None:
        self.params = config.planners.vs_global
        self.radius_m = config.scan.standoff_m
        self.activation_m = config.planners.vs.barrier_activation_m
        # the servo keeps the arm from lowering this further (ServoScanPlanner): a path below it is blocked
        self.min_singular_value = config.planners.vs.singular_value_activation
        self.goal: Array | None = None
        self.goal_value = float("nan")
        self._centre = np.zeros(3)  # the centroid the goal was sampled around [m], base frame
        self._goal_since = 0.0
        # (job time [s], distance to the goal [m]) over the last stall_time_s, for the progress rule
        self._distances: deque[tuple[float, float]] = deque()
        self.n_goals = 0

    def sample(self, session: ScanSession, centroid: Array, objective: EntropyObjective) -> None:
        """Choose a new goal: the best allowed candidate on the sphere around ``centroid`` (eq. 10), at
        least ``arrival_m`` [m] from the camera."""
        u = session.rng.normal(size=(self.params.n_candidates, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        views = sphere_views(centroid, self.radius_m, u)
        here = session.sensor_pose()[:3, 3]
        # A candidate within arrival_m of the camera is a goal already reached (``done`` would report it at
        # the next iteration): it moves the camera nowhere, and Global's best candidates lie just around a
        # camera whose view is not yet used up (goals "reached after 0.0 s").
        allowed = session.sensor_poses_allowed(views) & (
            np.linalg.norm(views[:, :3, 3] - here, axis=1) >= self.params.arrival_m)
        if not allowed.any():
            raise PlanningError(f"none of {len(views)} goal candidates on the {self.radius_m:g} m sphere "
                                f"lies inside the barrier planes and the workspace, "
                                f"{self.params.arrival_m:g} m or more from the camera")
        views = views[allowed]
        scores = objective(views)
        order = np.argsort(-scores, kind="stable")
        best = self._reachable(session, centroid, views, order)
        self.goal, self.goal_value = views[best], float(scores[best])
        self._centre = np.array(centroid, dtype=np.float64)
        self._goal_since = session.now()
        self._distances.clear()
        self.n_goals += 1
        session.log(f"goal {self.n_goals}: sensor at {np.round(self.goal[:3, 3], 3).tolist()}, f "
                    f"{self.goal_value:.4f} nats (rank {int(np.flatnonzero(order == best)[0]) + 1} of "
                    f"{order.size} allowed candidates)")

    def _reachable(self, session: ScanSession, centroid: Array, views: PoseBatch,
                   order: NDArray[np.intp]) -> int:
        """The index of the first candidate in ``order`` that the arm can servo to (module docstring),
        checking at most ``reachability_checks`` of them; a candidate within ``arrival_m`` of one that
        failed is skipped unchecked, as the same goal. None reachable (or no checks): the first."""
        checks = self.params.reachability_checks
        if not checks:
            return int(order[0])
        here = session.sensor_pose()
        positions = views[:, :3, 3]
        same_as_failed = np.zeros(len(views), dtype=bool)
        n_checked = 0
        for k in order:
            if same_as_failed[k]:
                continue
            path = arc_views(centroid, self.radius_m, here, positions[k], self.params.path_step_m)
            if session.sensor_path_reachable(path, self.min_singular_value):
                return int(k)
            same_as_failed |= np.linalg.norm(positions - positions[k], axis=1) < self.params.arrival_m
            n_checked += 1
            if n_checked == checks:
                break
        session.log(f"none of the {n_checked} goal candidates checked (best first, one per "
                    f"{self.params.arrival_m:g} m) is reachable from the present joints; servoing towards "
                    "the best")
        return int(order[0])

    def done(self, session: ScanSession, T_base_cam: Array) -> bool:
        """The goal was reached (within ``arrival_m``), given up (no progress of ``stall_progress_m`` within
        ``stall_time_s``), or there is none. Called once per servo iteration."""
        if self.goal is None:
            return True
        p = self.params
        now = session.now()
        elapsed = now - self._goal_since
        if float(np.linalg.norm(self.goal[:3, 3] - T_base_cam[:3, 3])) < p.arrival_m:
            session.log(f"goal {self.n_goals} reached after {elapsed:.1f} s")
            return True
        d = self.radius_m * angle_between(T_base_cam[:3, 3] - self._centre, self.goal[:3, 3] - self._centre)
        self._distances.append((now, d))
        # keep one sample at or before the start of the window: the distance stall_time_s ago
        while len(self._distances) > 1 and self._distances[1][0] <= now - p.stall_time_s:
            self._distances.popleft()
        t_then, d_then = self._distances[0]
        if t_then <= now - p.stall_time_s and d_then - d < p.stall_progress_m:
            session.log(f"goal {self.n_goals} given up after {elapsed:.1f} s, {d:.3f} m away on the sphere: "
                        f"{max(d_then - d, 0.0) * 1e3:.1f} mm closer in the last {p.stall_time_s:g} s")
            return True
        return False

    def __call__(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective) -> Secondary:
        """g of eq. 11 towards the current goal, projected to the barrier-feasible set."""
        assert self.goal is not None
        p = T_base_cam[:3, :3].T @ (self.goal[:3, 3] - T_base_cam[:3, 3])  # goal origin, camera frame
        d = float(np.linalg.norm(p))
        xy = float(np.hypot(p[0], p[1]))
        direction = np.zeros(3)
        if xy > 0.0:
            direction[:2] = p[:2] / xy * min(1.0, d / self.params.slow_radius_m)
        direction = session.feasible_sensor_velocity(direction, self.activation_m)
        f = float(objective(T_base_cam))
        return Secondary(np.concatenate([direction, np.zeros(3)]), float(np.linalg.norm(direction)), f,
                         "global")


class VSGlobalPlanner(ServoScanPlanner):
    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        self.goals = GoalSeeker(config)

    def secondary(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective,
                  rows: Array) -> Secondary:
        if self.goals.done(session, T_base_cam):
            if self.goals.goal is not None:
                self.open_entropy_window()  # the first goal reached or given up
            assert self.centroid is not None
            self.goals.sample(session, self.centroid, objective)
        return self.goals(session, T_base_cam, objective)

    def finished(self, session: ScanSession) -> str | None:
        return self.entropy_settled()
