"""VS-Local (visual-servoing paper section II-B 2, eq. 4-6): ascend the gradient of f in the camera's
xy-plane, tangent to the sphere of radius Z* that the primary task keeps the camera on.

The gradient (df/dx, df/dy) of eq. 4 comes from central differences over delta = 5 cm along the camera's
x and y (eq. 5-6: four evaluations of f, plus f(r) itself, in one batch). It is rescaled (the paper's
alpha) into g = alpha (df/dx, df/dy, 0, 0, 0, 0) / (f(r) + f_eps), projected into the set the barrier
planes allow (``session.feasible_sensor_velocity``), so the camera slides along a plane (paper Fig. 3),
and its norm is clipped to 1: a direction rather than a speed.

Convergence: ||g|| < 1 in more than 80 % of the last 200 evaluations. The norm judged is the one after
the barrier projection and before clipping, the quantity of the paper's Fig. 4, which drops when the
camera reaches a plane; the servo loop further scales it by the share of the commanded motion the arm
realizes (``ServoScanPlanner.run``), so a camera held by a joint limit or by the arm's reach converges as
one held by a plane does, instead of pressing against it until the time budget ends (a dragon placed
at (8, -6) cm, 45 deg from the station: the stretched arm moved the camera at 4 % of the commanded
speed from 75 s on, and the scan ran to its 180 s budget).

A camera held by a direction the guard refused (``ServoScanPlanner._back_off``: the arm retraces 1 s of its
path and g may not point the refused way within ``refusal_radius_m``) is not converged: the gradient still
leads there, the arm only could not take it in its present configuration. An evaluation whose difference
over delta the refused directions alone cut below ``g_max`` (``Secondary.refused``) does not count towards
convergence, and a window that would have converged with them ends the scan "held by a refused motion"
instead (``held``). A mug (RGB-D cell, seed 0) was refused at 21.9 s (link1 would touch link5b), retraced
to 4.2 cm from that place, and its ||g|| fell from 3 to 0.04 and then 0 there while the difference over
delta still pointed the refused way: the scan ended "converged" at 80.8 % 4 s later. VS-Local has no other
way round (VS-Hybrid's global goals are one); it now ends there saying why.

Going to and fro (``dithering``, not in the paper): a camera that stayed within delta of its mean
position over a whole window never left the stencil of eq. 5-6 (views delta either side) that judged
the spot: the differences it followed there were of views overlapping each other's, noise however large
||g|| is. The spot's difference over delta then counts as flat: the camera holds, and the longer arcs
below decide whether it moves on or the scan converges. If an arc offers a way on, the camera follows
the arcs until it is that arc's length from the spot (``_spot``): the arc said f is higher there, not
half way, and within that distance the difference over delta would pull it back to the spot it has used
up. A Table I bunny (seed 0) went to and fro from 21 to 65 s, online coverage stuck at 83 %, before it
happened to leave (97.4 % at 90 s); with the rule it leaves at once (96.8 % at 75 s). A held-out
horizontal box (20 deg yaw, seed 0) went to and fro 20 cm over its top from 20 s to its 180 s budget
within 1-3 cm of one spot, ||g|| 1.0-1.5 with its direction turning over and f flat at 0.022 nats, its
sides unseen: with the rule as first written (a ball of delta / 2, no commitment) the
arcs showed it the way out, and once out of the ball the difference over delta pulled it back. Now it
leaves, reaches the sides and converges at 34 s with 66 % (55 % before): the views that see the rest of
its sides, 10-20 deg above the table, pass within a few centimetres of its corners on the Z* = 25 cm
sphere (a 30 x 20 cm box), where the guard refuses the camera (``camera would touch object ROI``).

The rescaling departs from the paper. Its alpha = 1e-4 multiplies the gradient of its implementation's f,
whose scale it does not give: with f as eq. 9 writes it (mean over the K rays, nats) alpha = 1e-4 gives
||g|| ~ 1e-3 and the rule would end every scan at once. A fixed alpha on the absolute gradient does not
transfer between objects either: f of a 7 cm ball is ten times smaller than f of the 15 cm bunny, and so
is its gradient. Dividing by f(r) makes g the relative gradient, d ln f / dx [1/m], independent of the
object's size, the map resolution and the ray count; alpha [m] = 1 ends the scan once a 5 cm move would
change f by less than 5 %.

``f_eps_nats`` keeps the ratio finite where no ray meets the ROI and sets the level of f below which a view
counts as exhausted: the noise floor of the map. Once the object's surface is known, what is left of f
(``ObjectiveConfig.voxel_entropy``: residual) is the voxels a surface crosses at a slant. Across views some
rays end in them and some pass through, and they stay at p = 0.2-0.8 however often they are seen; f at the
current view is then made of them (0.005-0.03 nats in the tails of Table I's and the held-out scans, more on
curved objects), and a 5 cm step can change which of them the rays at the edge of the view meet by as much
as f itself: a relative gradient of up to 10 f / (f + f_eps) [1/m], above 1 wherever f exceeds f_eps / 9,
and a scan wanders on that noise at full speed until it happens to end. The default, 0.03, is the RGB-D
cells' value before their 1 cm margin; they now use 0.05 (the simulated ToF cell: 0.001). Measured on the
RGB-D cell with its 1 cm ROI margin (``benchmarks/vs_table.py``, ``cell eval heldout``): at 0.03,
8 of Table I's 8 objects reached the paper's coverage with a mean scan time of 45.2 s (seed 0); at
0.05, 7 of 8 in 39.3 s (seed 0) and 40.4 s (seeds 1 and 2): the cube's arc from one side over the top to the
other ends at 82 % (paper 92.2 %), the arc the paper describes for its Local cube scans. On ten shapes and
placements outside Table I, 0.05 against 0.03: mean scan time 47.2 against 51.4 s, coverage 87.0 against
88.3 %. At 0.1 (3 cm margin) the banana and baseball scans ended below the paper's coverage (67.5 %,
71.3 %).

With the observation-aware entropy (``ObjectiveConfig.entropy``, the default) those voxels fade from f as
they are seen again (their weight falls like 1 / n), so that f at a view whose surroundings are known
falls well below f_eps (0.003 nats at the end of a dragon scan, 0.013 with the paper's form), and the
noise on which the scans wandered goes with it. f_eps then only says how much a 5 cm move must reveal
to be worth making, f_eps / 20 = 0.0025 nats: about two rays meeting one unseen voxel each (ln 2 / K =
0.0013 nats per ray, K = 529); it is kept at 0.05.

Coarse differences (``reach_deg``, a departure from eq. 5-6). The camera uses up the information of the
views around it: whatever it sees is observed again at every capture, so f at the view, and within delta
of it, falls to the map's floor while the rest of the sphere keeps its information. On Table I's dragon
(seed 0, calibration error on) the camera climbed from the sideways start view, was held by the Panda's
elbow (joint 4 at its margin) while moving towards the robot, slid down along that limit, and after 17 s
sat at a view with f = 0.001 nats, f = 0.005-0.008 at +-5 cm (the view itself in a dip: lower than both
neighbours along x), and 0.1-0.16 on the far side of the object, 90-150 deg away on the sphere. Eq. 5-6's
difference there is flat to within a few rays meeting one voxel: ||g|| < 1, and the scan ended
"converged" with 70.6 % coverage of a 95.4 % limit (70.7 % with the error off, ``sim.exact``: the error
is not the cause). That was no local maximum but a plateau as wide as the part of the sphere already
seen, and neither the termination nor f_eps can tell the two apart: with f_eps at one ray meeting one
unseen voxel (0.0013 nats), ||g|| stayed above 1 on the plateau's noise and the camera dithered in place
until the time budget (177 s, 71.9 %); taking the steeper one-sided difference out of the dip instead
wandered on the same plateau (69.7 % at 50 s). So, before an evaluation counts towards convergence,
the camera looks over longer arcs of the sphere, 2, 3, ... times delta's up to ``reach_deg`` (23, 34, 46,
... 90 deg at Z* = 25 cm): the virtual displacements of eq. 5-6, and the diagonals between them, turned
about the point the camera looks at, so that their views still hold the object, and the camera turned
round the vertical through that point both ways, staying at its height (``orbited``). It heads for the
one view among them
whose f exceeds f(r) most per metre of arc, (f(view) - f(r)) / arc, judged on the part of its direction
the camera can follow (``ServoScanPlanner.follows``: barrier planes, joint limits, the edge of the reach)
as the convergence window is, with the relative scaling above; a view beyond a barrier plane (under the
table, past the reach) is none the camera can take and is not a candidate. The camera still moves
continuously along the sphere. Two forms were tried first and dropped. The central difference of each
arc, the shortest that reached 1 leading: a held-out horizontal box's camera went to and fro between a
short arc's small rise on one side and a longer arc's steep one on the other (a few centimetres towards
the steep one and the short one led again), to its 180 s budget. The same, the steepest arc leading: a
view beyond a barrier plane then had to count as the current one (with the views under the table
counted, mustard, bunny and teapot scans on the floor plane had dithered along it, towards the unseen
underside), which made a long arc's difference one-sided and steep next to a shorter arc's two-sided one
in the opposite direction, and a held-out mustard bottle went to and fro between the two and converged
at 85 % (99.8 % before). The views move with the camera, so the best one can change sides as it moves: in
a valley between two ridges both sides rise, and a centimetre towards one made the other the steeper (a
Table I bunny went to and fro between its +y and -y views to its 180 s budget in all three seeds). So
the side last headed for (``_heading``) is kept while it still offers a rise of g_max, and the best of
all is taken again once it does not or the difference over delta leads. The diagonals and the level
circle came last: with +x, -x, +y and -y alone, a camera 10 deg above the table, rolled so that its x was
level, had one great circle that stayed above the table (its y pointed straight up and down), and a
quarter turn along it ended just short of the unseen side: a Table I cube (seed 1) converged after its
arc over the top at 82 %, and two banana scans 40-45 deg from views that would see their unseen side
(91.5 and 89.2 %); with them the cube reaches 100 % and the bananas 99.6 % (Table I, seeds 0-2: every
object's mean coverage at least 0.96 of its upright-view limit, see below, mean scan time 37.3 s against
32.4 s).

The arcs grow by delta's rather than doubling: from a camera high over the object the views 90 deg away lie
under the table and those 46 deg away still look at the known top, and a dragon scan converged there with the
unseen lower sides in between (87.6 %). With arcs up to a quarter turn the scan ended where f is flat at
every scale up to 90 deg, beyond which a displaced view looks at the sides the current one cannot see: a
local maximum at the scale of the object rather than of delta.
``reach_deg`` 0 is the paper's single delta; VS-Hybrid keeps that (its global goals are its way off a
plateau). Table I, seed 0, calibration error on (``cell eval vs-table --planners vs-local --seeds 0``),
coverage of the limit with 90 deg against 0 (the limit of views held upright, which ``cell.evaluation.limit``
gave before a view's roll was free, up to 3 points below today's): banana 0.82 / 0.71, baseball 0.91 / 0.84,
bunny 0.98 / 0.96, cube 1 / 1, dragon 0.94 / 0.74, mustard 1 / 0.96, pyramid 1 / 1, teapot 0.94 / 0.92; the
mean scan time rose from 33.9 to 53.4 s (bunny 94 s, mustard 78 s: the camera goes on round the object). Those
were at the paper's exploration speed, 1.9 cm/s; at the RGB-D cells' 5 cm/s (``ServoConfig.lambda_g``) the
camera gets round the object well before the arcs run out of scale.

Half a turn, crossed at the arc's scale. A quarter turn was not enough for the teapot on the Panda (Table I,
seeds 0-2: 92.4-93.5 % of its 99.7 % limit, ``cell.evaluation.limit``): the camera climbed from the start view
over the top to the unseen side, slid along the floor plane towards the robot, and was held at azimuth 146 deg
(seen from the object, 0 beyond it) by a refused motion (link1 against link5b) and the elbow's margin (joint
4), with the lower body under the spout unseen 150 deg round, beyond the sectors the arm cannot take low (its
base, the plane of its maximum reach); an oracle map, in which the unseen surface stayed unknown, ended the
same way. With arcs up to 175 deg, a half turn short of the antipode where every great circle meets, the
camera compares views as far as the far side of the object all along the scan, and every Table I object
reached at least 0.98 of its limit, the teapot 0.982; but the mean scan time rose from 36.2 to 48.0 s. Most of
it (bunny, seed 0: 39 of 66 s; cube 37 of 58 s; teapot, seed 2: 98 of 128 s) was spent led by a longer arc,
crossing views the camera had used up at the exploration speed, whose rule is delta per perception period
because the difference over delta judges views delta apart (``ServoConfig``). By the same rule, while the arc
of k deltas leads, the camera moves at k times that speed (``Secondary.speed``), up to the cell's TCP speed
limits (linear, and angular about the object at Z*: 5 times, 25 cm/s, on the simulated RGB-D cell, twice on
the Franka template's 0.1 m/s); the convergence window judges ||g|| against the exploration speed
(``held_norm``), so a crossing the guard's speed limits slow is not taken for a held camera; near a joint's
margin or a barrier plane it slows to the exploration speed (``ServoScanPlanner._limits_ahead``). Table I,
seeds 0-2, calibration error on (``benchmarks/vs_table.py``), coverage of the limit: banana 0.995, baseball
0.996, bunny 0.993, cube 1, dragon 0.989, mustard 1, pyramid 1, teapot 0.962 (99.7, 92.9 and 95.2 %), mean
scan time 40.2 s. On fifteen shapes and placements outside Table I (``cell eval heldout``, seed 0) against a
quarter turn: mean coverage 92.7 against 93.1 %, mean scan time 38.3 against 36.9 s; a standing ring 97.5
against 89.1 %, a mushroom 89.2 against 80.7 %, a torus 86.5 against 97.8 %, and a cup 59.8 against 88.0 %: it
converged on the floor plane on the side it had climbed to, the thin walls' case of
``cell.planning.vs.objective``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from cell.config.models import CellConfig
from cell.control.servo import exploration_speed_mps
from cell.planning.base import Array, ScanSession
from cell.planning.vs.objective import EntropyObjective, PoseBatch
from cell.planning.vs.servo_scan import Secondary, ServoScanPlanner, translated

# The directions (unit, camera xy-plane) of the great circles the coarse arcs turn the camera along: +x, -x,
# +y, -y as the virtual displacements of eq. 5-6, and the four diagonals between them (the camera can move
# in any direction of its xy-plane).
SIDES = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0],
                  [1.0, 1.0, 0], [-1.0, -1.0, 0], [1.0, -1.0, 0], [-1.0, 1.0, 0]])
SIDES /= np.linalg.norm(SIDES, axis=1, keepdims=True)


def orbited(T_base_cam: Array, radius_m: float, angle_rad: float) -> tuple[PoseBatch, Array]:
    """``T_base_cam`` turned by ``angle_rad`` about the point ``radius_m`` [m] ahead on its optical axis, so
    that it stays on the sphere of that radius around the point and still looks at it (the virtual
    displacements of eq. 5-6 over an arc of ``angle_rad * radius_m``): along the great circles towards each
    of its :data:`SIDES`, then along the circle of its height both ways (about the base's +z, then -z).
    From a view low on the sphere, looking down at the point, the great circles through it turn down
    towards the table, the level one too, except those climbing over the top, which stay on the near side
    within a quarter turn; the circle of the camera's height goes round the object at the height it is at.

    Returns the poses (10, 4, 4) and the directions (10, 3) they start out in, unit in the camera frame
    (zero for the circle of its height when the camera looks straight down: it has none)."""
    R0, p = T_base_cam[:3, :3], T_base_cam[:3, 3]
    pivot = p + radius_m * R0[:, 2]
    # about the unit axis (-z) x u the direction from the pivot to the camera (-z) turns towards u
    axes = np.concatenate([np.cross(-R0[:, 2], SIDES @ R0.T), [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
    tangents = np.cross(axes, p - pivot) @ R0  # camera frame, radius_m long on the great circles
    lengths = np.linalg.norm(tangents, axis=1, keepdims=True)
    directions = np.divide(tangents, lengths, out=np.zeros_like(tangents), where=lengths > 1e-9 * radius_m)
    out = np.repeat(T_base_cam[None], len(axes), axis=0)
    for i, axis in enumerate(axes):
        R = Rotation.from_rotvec(angle_rad * axis).as_matrix()
        out[i, :3, :3] = R @ R0
        out[i, :3, 3] = pivot + R @ (p - pivot)
    return out, directions


class LocalGradient:
    """Eq. 4-6 with the scaling, projection and clipping of section II-B 2, and the convergence window."""

    def __init__(self, config: CellConfig, coarse: bool = True) -> None:
        self.params = config.planners.vs_local
        self.activation_m = config.planners.vs.barrier_activation_m
        self.standoff_m = config.scan.standoff_m
        d = self.params.delta_m
        # The fastest crossing, as a multiple of the exploration speed: the cell's TCP speed limits, linear
        # and (about the object at Z*) angular; the guard scales the flange's own twist down to them.
        safety, servo = config.safety, config.planners.vs.servo
        speed = exploration_speed_mps(servo.lambda_g, self.standoff_m)
        fastest = min(safety.tcp_max_linear_mps, safety.tcp_max_angular_rps * self.standoff_m)
        self._max_speed = max(1.0, fastest / speed) if speed > 0.0 else 1.0
        # The arcs [rad] of the coarse differences: 2, 3, ... times delta's, the last one at reach_deg.
        reach = np.deg2rad(self.params.reach_deg) if coarse else 0.0
        step = d / self.standoff_m
        n = int(np.ceil(reach / step - 1e-9))
        self._coarse_angles = tuple(min(k * step, reach) for k in range(2, n + 1))
        # r, r + dx, r - dx, r + dy, r - dy in the camera frame.
        self._offsets = np.array([[0, 0, 0], [d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0]], dtype=float)
        self._below: deque[bool] = deque(maxlen=self.params.window)
        # per evaluation of the window: below g_max only because a refused direction held the camera
        self._refused: deque[bool] = deque(maxlen=self.params.window)
        self._where: deque[Array] = deque(maxlen=self.params.window)
        # (spot [m, base frame], distance [m]): a spot gone to and fro on, and how far from it the
        # arcs lead before the difference over delta is followed again
        self._spot: tuple[Array, float] | None = None
        # the side of the camera (an index of orbited's four displacements) the coarse arcs last led to
        self._heading: int | None = None

    def reset(self) -> None:
        """Forget the convergence window and any spot (a new local phase)."""
        self._below.clear()
        self._refused.clear()
        self._where.clear()
        self._spot = None
        self._heading = None

    def __call__(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective,
                 feasible: Callable[[Array], Array] | None = None,
                 unrefused: Callable[[Array], Array] | None = None) -> Secondary:
        """g at ``T_base_cam``. ``feasible`` maps a direction (3,) in the camera frame to the part of it the
        camera can follow (default: without its components into the barrier planes); the coarse arcs are
        judged on that part, as the convergence window is. ``unrefused`` is ``feasible`` without the
        directions the guard refused nearby (``ServoScanPlanner.follows``): where ``feasible`` cuts the
        difference over delta below ``g_max`` and ``unrefused`` does not, g is marked ``refused``, and
        ``record`` does not count it as converging (module docstring)."""
        p = self.params
        if feasible is None:
            def feasible(v: Array) -> Array:
                return session.feasible_sensor_velocity(v, self.activation_m)
        f = objective(translated(T_base_cam, self._offsets))
        grad = np.array([f[1] - f[2], f[3] - f[4], 0.0]) / (2.0 * p.delta_m)  # eq. 5-6 [nats/m]
        relative = p.alpha * grad / (f[0] + p.f_eps_nats)  # d ln f / dx, see the module docstring
        direction = feasible(relative)
        norm = float(np.linalg.norm(direction))
        refused = unrefused is not None and norm < p.g_max <= float(np.linalg.norm(unrefused(relative)))
        position = T_base_cam[:3, 3]
        if self._spot is not None and np.linalg.norm(position - self._spot[0]) >= self._spot[1]:
            self._spot = None  # the arc's length away: the difference over delta leads again
        leaving, dithering = self._spot is not None, self.dithering()
        if leaving or dithering:  # the difference over delta is noise here: not followed
            direction, norm = np.zeros(3), 0.0
        speed = 1.0
        if norm >= p.g_max:
            self._heading = None  # the difference over delta leads
        elif self._coarse_angles:  # flat at delta: the views over longer arcs
            coarse, angle = self._best_arc_view(session, T_base_cam, objective, float(f[0]), feasible)
            if float(np.linalg.norm(coarse)) >= p.g_max:
                direction, norm = coarse, float(np.linalg.norm(coarse))
                speed = min(angle * self.standoff_m / p.delta_m, self._max_speed)  # the arc's deltas
                if not leaving and dithering:
                    self._spot = (self._mean_position(), angle * self.standoff_m)
        clipped = direction * (p.g_max / norm) if norm > p.g_max else direction
        return Secondary(np.concatenate([clipped, np.zeros(3)]), norm, float(f[0]), "local", speed, refused)

    def _best_arc_view(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective, f_r: float,
                       feasible: Callable[[Array], Array]) -> tuple[Array, float]:
        """The relative rise of f (3,) towards the coarse arcs' view whose f exceeds ``f_r`` most per metre of
        arc in the part of its direction the camera can follow (``feasible``), that part, and that view's arc
        [rad]; zero if no view exceeds it. A view beyond a barrier plane (under the floor, past the reach) is
        none the camera can take, judged as far into the plane's margin as a motion from here may go: a camera
        sliding along the floor plane is inside its margin, and so is every view at its height (held on the
        floor, a held-out cup scan had none of its level circle's views counted). While the side last headed
        for (``_heading``: one of :func:`orbited`'s ways round) still offers a rise of ``g_max``, its best
        view is kept (module docstring)."""
        p = self.params
        orbits = [orbited(T_base_cam, self.standoff_m, a) for a in self._coarse_angles]
        views = np.concatenate([v for v, _ in orbits])
        allowed = session.sensor_poses_allowed(views, from_here=True)
        arcs = np.array(self._coarse_angles)
        gain = np.where(allowed, objective(views) - f_r, 0.0).reshape(len(arcs), -1)  # (angle, way round)
        rise = gain / (arcs[:, None] * self.standoff_m)  # [nats/m]
        # The part of a direction the camera can follow scales with it (half-spaces through the origin), and
        # a way round keeps its direction at every angle: its steepest view is the one followed furthest.
        side_best = []
        for i, direction in enumerate(orbits[0][1]):
            k = int(np.argmax(rise[:, i]))
            g = p.alpha * float(rise[k, i]) * direction / (f_r + p.f_eps_nats)
            side_best.append((feasible(g) if rise[k, i] > 0.0 else np.zeros(3), float(arcs[k])))
        norms = [float(np.linalg.norm(g)) for g, _ in side_best]
        if self._heading is None or norms[self._heading] < p.g_max:
            best = int(np.argmax(norms))
            self._heading = best if norms[best] >= p.g_max else None
        return side_best[self._heading] if self._heading is not None else side_best[int(np.argmax(norms))]

    def record(self, g_norm: float, position_m: Array, refused: bool = False) -> None:
        """Count one servo evaluation whose ||g|| (before clipping, as the arm could follow it) was
        ``g_norm``, made with the camera at ``position_m`` (3,) [m, base frame]; ``refused``: g was held
        below ``g_max`` by a refused direction (``Secondary.refused``)."""
        below = g_norm < self.params.g_max
        self._below.append(below)
        self._refused.append(below and refused)
        self._where.append(np.asarray(position_m, dtype=float).reshape(3))

    def _mean_position(self) -> Array:
        """The camera's mean position (3,) [m, base frame] over the window."""
        return np.asarray(np.mean(np.array(self._where), axis=0))

    def dithering(self) -> bool:
        """Over a full window of evaluations the camera stayed within delta of its mean position (module
        docstring)."""
        if len(self._where) < (self._where.maxlen or 0):
            return False
        spread = np.linalg.norm(np.array(self._where) - self._mean_position(), axis=1)
        return float(np.max(spread)) <= self.params.delta_m

    def converged(self) -> bool:
        """||g|| < g_max, not held there by a refused direction, in more than ``converged_fraction`` of a
        full window of evaluations."""
        w = self._below
        return len(w) == w.maxlen and sum(w) - sum(self._refused) > self.params.converged_fraction * len(w)

    def held(self) -> bool:
        """||g|| < g_max in more than ``converged_fraction`` of a full window of evaluations, but not
        converged: a refused direction held the camera in enough of them (module docstring)."""
        w = self._below
        full = len(w) == w.maxlen and sum(w) > self.params.converged_fraction * len(w)
        return full and not self.converged()


class VSLocalPlanner(ServoScanPlanner):
    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        self.local = LocalGradient(config)

    def secondary(self, session: ScanSession, T_base_cam: Array, objective: EntropyObjective,
                  rows: Array) -> Secondary:
        # what the camera could follow but for the refusals nearby: tells a camera they hold from one that
        # converged
        near = self._refusals_at(T_base_cam)
        unrefused = self.follows(session, T_base_cam, rows, refusals=False) if near else None
        return self.local(session, T_base_cam, objective, self.follows(session, T_base_cam, rows), unrefused)

    def observe(self, secondary: Secondary, g_norm: float, position_m: Array) -> None:
        self.local.record(g_norm, position_m, secondary.refused)

    def finished(self, session: ScanSession) -> str | None:
        p = self.config.planners.vs_local
        window = (f"||g|| < {p.g_max:g} in more than {p.converged_fraction:.0%} of the last {p.window} servo "
                  "evaluations")
        if self.local.converged():
            return f"local gradient converged: {window}"
        if self.local.held():
            near = "; ".join(sorted({why for _, _, why in self._refusals_at(session.sensor_pose())}))
            return (f"held by a refused motion, not converged: {window}, the camera kept from where the "
                    f"gradient leads by a direction the guard refused nearby{f' ({near})' if near else ''}")
        return None
