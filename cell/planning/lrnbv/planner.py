"""Algorithm 1 of the LR-NBV paper (section 3.1): a receding-horizon RRT of sensor poses with cached nodes.

Each iteration i:

- ExpandRRT (line 7): a tree T^i grows from the current sensor pose by ``samples_per_iteration`` RRT
  extensions (steps of ``rrt_step_m`` towards positions drawn in the robot workspace box within
  ``view_distance_m`` of the object); a node keeps the orientation that maximises U among look
  directions towards the ROI, and is dropped when ``session.sensor_pose_allowed`` refuses it (barrier
  planes, workspace) or it comes closer than ``object_clearance_m`` to the object's box;
- the best branch B^i maximises the cumulative utility of its nodes (eq. 1), x* is its best node
  (line 9) and U(x*) the figure lines 10 and 15 compare; the other nodes with U > tau join the cached
  nodes C (line 8);
- when x* is worse than the best cached node, ExpandRRTCached (line 11) grows a second tree whose
  samples are drawn around the cached nodes, and x* is taken from it;
- when U(x*) exceeds the worst cached node's utility (line 15) the arm captures along B^i
  (captureData(B^i), line 16, :meth:`RRTViewPlanner.capture_branch`) and the map is updated (lines
  17-18); otherwise the scan is complete (line 24). After the branch the cached nodes are re-scored on
  the new map, sorted and cut to m_i nodes, m_i decreasing linearly from ``cached_nodes`` to 1 over
  ``max_iterations`` (lines 19-21).

Choices the paper leaves open, and why:

- captureData(B^i) captures at the branch's nodes in order from the root, as line 16 and "the best
  branch is used to suggest the next poses" read, not only at x* nor only at the first node (Bircher et
  al.'s receding horizon, which the paper cites for re-planning a new tree each iteration). Every node
  after the first is re-scored on the map its predecessors' captures left and skipped when its U is no
  longer above tau: with the visited gain a node in a coarse cell the branch has just visited scores
  about -w_v and is not captured again; without it (``nbv``) U stays positive. This is what makes the
  baseline take more, and more redundant, poses (the paper's useless poses, section 4.2). ``capture:
  best_node`` captures at x* alone instead.
- tau (``cache_threshold``) is 0: with the visited gain a node in a visited cell scores about -w_v and
  is neither cached nor captured; any other node is worth remembering.
- Best and worst cached nodes come from the re-scoring after the last capture, as in lines 20-21; before
  the first re-scoring, and after one that kept no node (every cached node out of reach), there is no
  threshold and the scan goes on: the argmax and argmin of an empty C^i are no node, and a threshold
  kept from nodes the cache has dropped would end the scan on views it can no longer offer. m_i counts
  planning passes i, so with Table 1's 300 iterations it stays near 50 over a scan of tens of
  iterations, as the paper's figures imply.
- The cached nodes kept at line 19 are the best m_i the arm reaches (``session.sensor_view_reachable``:
  joints for the view, or for one of its same-view rolls, that a move to it would try, within the
  guard's bounds and free of collision; a node a move reaches only from the home seed, or rolled, is
  one the arm reaches). Algorithm 1 caches utilities only; kept regardless of reach, the far side of an
  object beyond the arm's reach holds the cache's places with high utilities, the worst kept node (line
  21) is then a high one and the scan completes early (a vertical box at seed 14 completed after 8
  captures, IoU 0.71). A node is checked once, when it first ranks among those kept.
- G_v's grid (eq. 6) marks the coarse cell of the sensor position of every capture, the initial ones
  included.
- ``nbv`` is this same loop, termination included (section 4: it "follows the algorithm described in
  Algorithm 1"), with w_d = w_v = 0.
- A move the session refuses (no IK solution, collision, barrier) ends that branch's captures and counts
  a failed move; ``max_failed_moves`` in a row end the scan. Its position is remembered: nodes within
  ``refused_radius_m`` of it are dropped from later trees and from the cache, or the unseen far side of
  an object just beyond the arm's reach would draw every tree back to it. The iteration budget counts
  planning passes, so a scan always ends.
- The RRT draws from the job's planner generator (``ScanSession.rng``, a stream of the job seed), so the
  same config, object and job seed give the same scan, and other seeds other trees.
- Before Algorithm 1 starts (inputs A^0, C^0) the planner captures at the current pose; while no object
  is found it looks down at the station from each of ``search_heights_m`` in turn: a small object seen
  from far by an 8 x 8 sensor fills fewer zones than a cluster needs. Then, while still none is found,
  from each pose of the cell's ``heu`` ellipse around the station (:func:`heu_views`): a narrow upright
  part seen from above fills too few zones however close (a 6 cm spire 15 cm tall left 6 voxels in the
  first view and the two from above, where a cluster needs ``min_cluster_points``, 10), and from the
  side its height fills more. No object in any of those views ends the scan with ``NoObjectFound``
  (the job ends ``no_object``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from cell.config.models import CellConfig
from cell.packing.result import ReconstructionHistory
from cell.planning.base import Array, Planner, ScanSession
from cell.planning.lrnbv.config import LRNBVConfig
from cell.planning.lrnbv.heu import heu_views
from cell.planning.lrnbv.sensor import sensor_rays
from cell.planning.lrnbv.utility import UtilityField, VisitedGrid, Weights, evaluate
from drivers.depth.base import SensorModel
from drivers.errors import NoObjectFound
from drivers.robots import get_robot_model
from drivers.transforms import look_at, make_T


def look_at_rotations(eyes: Array, targets: Array) -> Array:
    """R_base_sensor (N, 3, 3) of sensors at ``eyes`` (N, 3) looking at ``targets`` (N, 3): the
    convention of ``drivers.transforms.look_at`` (z to the target, image up = +z of the base frame, or +x
    when looking straight up or down), for many poses at once."""
    z = targets - eyes
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    up = np.tile([0.0, 0.0, 1.0], (z.shape[0], 1))
    up[np.abs(z[:, 2]) > 1.0 - 1e-6] = [1.0, 0.0, 0.0]
    x = np.cross(z, up)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)


@dataclass
class Tree:
    """An RRT of sensor poses: ``positions`` (N, 3), ``rotations`` (N, 3, 3), ``utility`` (N,) with -inf
    for refused nodes, ``parent`` (N,) index, -1 for the root (node 0, the current pose)."""

    positions: Array
    rotations: Array
    utility: Array
    parent: np.ndarray

    def best_branch(self) -> list[int]:
        """Eq. 1: the root-to-node path (root excluded) of maximal cumulative utility."""
        n = self.positions.shape[0]
        cum = np.zeros(n)
        for i in range(1, n):  # parents always precede their children
            cum[i] = cum[self.parent[i]] + self.utility[i]
        cum[0] = -np.inf
        end = int(np.argmax(cum))
        branch: list[int] = []
        while end > 0:
            branch.append(end)
            end = int(self.parent[end])
        return branch[::-1]


@dataclass
class CachedNodes:
    """The cached nodes C^i: positions (K, 3), orientations (K, 3, 3), utilities (K,), and ``reached``
    (K,): the arm was found to reach the node (False: not checked yet)."""

    positions: Array = field(default_factory=lambda: np.zeros((0, 3)))
    rotations: Array = field(default_factory=lambda: np.zeros((0, 3, 3)))
    utility: Array = field(default_factory=lambda: np.zeros(0))
    reached: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def append(self, positions: Array, rotations: Array, utility: Array) -> None:
        self.positions = np.vstack([self.positions, positions])
        self.rotations = np.concatenate([self.rotations, rotations])
        self.utility = np.concatenate([self.utility, utility])
        self.reached = np.concatenate([self.reached, np.zeros(utility.shape[0], dtype=bool)])

    def keep(self, which: np.ndarray) -> None:
        """Keep the nodes ``which`` selects (a mask, or indices in the order to keep them)."""
        self.positions, self.rotations, self.utility, self.reached = self.positions[which], \
            self.rotations[which], self.utility[which], self.reached[which]

    def __len__(self) -> int:
        return int(self.utility.shape[0])


class RRTViewPlanner(Planner):
    """Algorithm 1 with the gains its subclass enables (``lr-nbv``: all four; ``nbv``: G_e and G_q)."""

    section: ClassVar[str]
    uses_density_and_visited: ClassVar[bool]
    # set by prepare(), from the session, when a run starts
    rays: Array
    coarse_rays: Array
    rng: np.random.Generator

    def __init__(self, config: CellConfig) -> None:
        super().__init__(config)
        self.params: LRNBVConfig = getattr(config.planners, self.section)
        p = self.params
        self.weights = Weights(w_e=p.w_e, w_d=p.w_d if self.uses_density_and_visited else 0.0, w_q=p.w_q,
                               w_v=p.w_v if self.uses_density_and_visited else 0.0)
        self.resolution = config.perception.occupancy.resolution_m
        self.table_z = config.station.table_z_m
        ws = config.safety.workspace
        self.ws_min, self.ws_max = np.asarray(ws.min_m, dtype=float), np.asarray(ws.max_m, dtype=float)
        self.visited = VisitedGrid(p.visited_grid_m)
        self.reconstruction = ReconstructionHistory()
        self.n_failed_moves = 0
        self.n_refused_nodes = 0
        self.iteration = 0
        self.best_utility: float | None = None
        self.refused_positions = np.zeros((0, 3))

    def prepare(self, sensor: SensorModel, rng: np.random.Generator) -> None:
        """Before planning: the ray set of eqs. 3-4 from the connected sensor's geometry (every 2nd row
        and column of it for the coarse orientation search) and the generator the RRT draws from (the
        job's)."""
        grid = sensor_rays(sensor, self.params.rgbd_rays_per_side)
        self.rays = grid.reshape(-1, 3)
        self.coarse_rays = grid[::2, ::2].reshape(-1, 3)
        self.rng = rng

    # ------------------------------------------------------------------------------------- the map side
    def field(self, session: ScanSession, obj: Array) -> UtilityField:
        """U's map inputs for the current object O^i: ROI = its box grown by ``roi_margin_m``, not below
        the table."""
        m = self.params.roi_margin_m
        lo, hi = obj.min(axis=0) - m, obj.max(axis=0) + m
        lo[2] = max(lo[2], self.table_z)
        return UtilityField(session.perception.map, obj, lo, hi, resolution=self.resolution,
                            density_radius_m=self.params.density_radius_m,
                            observation_aware=self.params.exploration_weight == "observation")

    def look_targets(self, obj: Array) -> Array:
        """The points a node may look at: the object box centre and its corners pulled towards it."""
        lo, hi = obj.min(axis=0), obj.max(axis=0)
        centre = 0.5 * (lo + hi)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        spread = self.params.look_target_spread
        if spread <= 0.0:
            return centre[None]
        return np.vstack([centre, centre + spread * (corners - centre)])

    def score(self, f: UtilityField, targets: Array, positions: Array) -> tuple[Array, Array]:
        """Best orientation (N, 3, 3) and its utility (N,) for each position, over the look targets.

        The look targets are ranked with every other ray in each direction of the sensor grid (a quarter
        of the rays), then the winner is scored with all rays: the ranking needs the rough shape of the
        view, the score the full eq. 3-4 sums."""
        n, k = positions.shape[0], targets.shape[0]
        eyes = np.repeat(positions, k, axis=0)
        rot = look_at_rotations(eyes, np.tile(targets, (n, 1))).reshape(n, k, 3, 3)
        if k > 1:
            g = evaluate(f, self.visited, eyes, rot.reshape(-1, 3, 3), self.coarse_rays,
                         self.params.ray_length_m)
            best = np.argmax(self.weights.utility(g).reshape(n, k), axis=1)
        else:
            best = np.zeros(n, dtype=np.int64)
        chosen = rot[np.arange(n), best]
        g = evaluate(f, self.visited, positions, chosen, self.rays, self.params.ray_length_m)
        return chosen, self.weights.utility(g)

    # ------------------------------------------------------------------------------------------ the tree
    def _sample_position(self, centre: Array, around: Array | None) -> Array | None:
        """A position in the workspace box within ``view_distance_m`` of the object centre: uniform, or
        near a cached node (``around``, ExpandRRTCached). None after 100 misses."""
        lo_d, hi_d = self.params.view_distance_m
        lo = np.maximum(self.ws_min, centre - hi_d)
        hi = np.minimum(self.ws_max, centre + hi_d)
        for _ in range(100):
            if around is None:
                q = self.rng.uniform(lo, hi)
            else:
                jitter = self.rng.normal(0.0, self.params.rrt_step_m / 2.0, 3)
                q = around[self.rng.integers(around.shape[0])] + jitter
            in_box = bool(np.all(q >= self.ws_min) and np.all(q <= self.ws_max))
            if in_box and lo_d <= np.linalg.norm(q - centre) <= hi_d:
                return q
        return None

    def near_refused(self, positions: Array) -> np.ndarray:
        """Mask (N,) of the positions (N, 3) within ``refused_radius_m`` of one the session refused."""
        if self.refused_positions.shape[0] == 0:
            return np.zeros(positions.shape[0], dtype=bool)
        d = np.linalg.norm(positions[:, None, :] - self.refused_positions[None, :, :], axis=2)
        return np.asarray(np.any(d < self.params.refused_radius_m, axis=1))

    def _clear_of_object(self, p: Array, obj_lo: Array, obj_hi: Array) -> bool:
        c = self.params.object_clearance_m
        return not bool(np.all(p >= obj_lo - c) and np.all(p <= obj_hi + c))

    def expand(self, session: ScanSession, f: UtilityField, obj: Array, around: Array | None) -> Tree:
        """ExpandRRT (``around`` None) or ExpandRRTCached: a tree from the current sensor pose."""
        p = self.params
        root = session.sensor_pose()
        centre = f.object_centre
        obj_lo, obj_hi = obj.min(axis=0), obj.max(axis=0)
        positions = [root[:3, 3]]
        parents = [-1]
        for _ in range(p.samples_per_iteration):
            q = self._sample_position(centre, around)
            if q is None:
                continue
            pts = np.array(positions)
            near = int(np.argmin(np.linalg.norm(pts - q, axis=1)))
            d = q - pts[near]
            dist = float(np.linalg.norm(d))
            new = q if dist <= p.rrt_step_m else pts[near] + d * (p.rrt_step_m / dist)
            if not self._clear_of_object(new, obj_lo, obj_hi) or self.near_refused(new[None])[0]:
                continue
            if not session.sensor_pose_allowed(look_at(new, centre)):
                continue
            positions.append(new)
            parents.append(near)
        pos = np.array(positions)
        rot = np.empty((pos.shape[0], 3, 3))
        util = np.full(pos.shape[0], -np.inf)
        rot[0] = root[:3, :3]
        if pos.shape[0] > 1:
            rot[1:], util[1:] = self.score(f, self.look_targets(obj), pos[1:])
        for i in range(1, pos.shape[0]):
            if not session.sensor_pose_allowed(make_T(rot[i], pos[i])):
                util[i] = -np.inf
                self.n_refused_nodes += 1
        return Tree(positions=pos, rotations=rot, utility=util, parent=np.array(parents))

    def _cache_off_branch(self, tree: Tree, branch: list[int], cache: CachedNodes) -> None:
        """Line 8 / 12: nodes of the tree off the best branch with U > tau join C."""
        mask = tree.utility > self.params.cache_threshold
        mask[0] = False
        mask[branch] = False
        cache.append(tree.positions[mask], tree.rotations[mask], tree.utility[mask])

    def _rescore(self, session: ScanSession, f: UtilityField, obj: Array, cache: CachedNodes, m: int) -> None:
        """Line 19: re-score the cached nodes on the new map and keep the best ``m`` the arm reaches
        (``session.sensor_view_reachable``), best first. A node is checked once, in the orientation it
        has when it first ranks among those kept: later re-scorings turn it by degrees as the object's box
        grows, and each check is up to eight IK solves (a move to it is checked again)."""
        if len(cache) == 0:
            return
        cache.rotations, cache.utility = self.score(f, self.look_targets(obj), cache.positions)
        kept: list[int] = []
        for i in np.argsort(-cache.utility, kind="stable"):
            if len(kept) == m:
                break
            if not cache.reached[i]:
                T = make_T(cache.rotations[i], cache.positions[i])
                cache.reached[i] = session.sensor_view_reachable(T)
            if cache.reached[i]:
                kept.append(int(i))
        cache.keep(np.array(kept, dtype=np.int64))

    # ------------------------------------------------------------------------------------------ the scan
    def _capture(self, session: ScanSession) -> Array:
        session.wait(self.params.settle_s)
        session.capture()
        self.visited.mark(session.sensor_pose()[:3, 3])
        return self.reconstruction.record(session.perception)

    def search_views(self) -> list[Array]:
        """The sensor's home view (the arm's home joints and the cell's mount), where the run captures
        first, then the views it moves to while no object is found: straight down at the station from
        each of ``search_heights_m``, then the poses of the ``heu`` ellipse."""
        model = get_robot_model(self.config.arm.model)
        T_home = model.fk(model.home(self.config.arm.home_joints_rad))
        return [T_home @ self.config.mount.matrix(), *self._search_moves()]

    def _search_moves(self) -> list[Array]:
        """:meth:`search_views` after the home view: the views the run moves to while no object is found."""
        st = self.config.station
        target = np.array([st.xy_m[0], st.xy_m[1], self.table_z])
        above = [look_at(target + np.array([0.0, 0.0, height]), target, up_hint=np.array([1.0, 0.0, 0.0]))
                 for height in self.params.search_heights_m]
        return [*above, *heu_views(self.config)]

    def _initial_object(self, session: ScanSession) -> tuple[Array, int]:
        """The object from the current view, or else from the search views; and the captures made."""
        obj = self._capture(session)
        captures = 1
        for T in self._search_moves():
            if obj.shape[0]:
                break
            if session.move_to_sensor_pose(T):
                obj = self._capture(session)
                captures += 1
        return obj, captures

    def _node_utility(self, session: ScanSession, obj: Array, tree: Tree, i: int) -> float:
        """U of tree node ``i`` (its planned orientation) on the map and visited grid as they are now."""
        g = evaluate(self.field(session, obj), self.visited, tree.positions[i:i + 1], tree.rotations[i:i + 1],
                     self.rays, self.params.ray_length_m)
        return float(self.weights.utility(g)[0])

    def capture_branch(self, session: ScanSession, obj: Array, tree: Tree, branch: list[int]) -> tuple[
            Array, int, int]:
        """captureData(B^i) (line 16): the arm visits the branch's nodes from the root outwards and captures
        at each. A node after the first is first re-scored on the map and visited grid its predecessors'
        captures left, and skipped when its U is no longer above tau: with the visited gain (w_v = 500)
        this drops a node in a coarse cell the branch has just visited, and so a redundant pose; without
        it (``nbv``) U stays positive and the whole branch is captured.

        A move the session refuses (unreachable, collision, barrier) ends the branch, whose later nodes
        continue from a pose the arm did not reach, and its position joins ``refused_positions``.

        Returns the object after the last capture (``obj`` when none found one), the captures made and the
        moves refused (0 or 1)."""
        captured = refused = 0
        for n, i in enumerate(branch):
            if n > 0 and self._node_utility(session, obj, tree, i) <= self.params.cache_threshold:
                continue
            if not session.move_to_sensor_pose(make_T(tree.rotations[i], tree.positions[i])):
                refused += 1
                self.refused_positions = np.vstack([self.refused_positions, tree.positions[i]])
                break
            obj_new = self._capture(session)
            captured += 1
            if obj_new.shape[0]:
                obj = obj_new
        return obj, captured, refused

    def run(self, session: ScanSession) -> str:
        p = self.params
        self.prepare(session.sensor_model(), session.rng)
        obj, captures = self._initial_object(session)
        if obj.shape[0] == 0:
            raise NoObjectFound("no object segmented from the current view and the search views")
        cache = CachedNodes()
        best_c: float | None = None
        worst_c: float | None = None
        failed_in_row = 0
        for it in range(p.max_iterations):
            f = self.field(session, obj)
            tree = self.expand(session, f, obj, None)
            branch = tree.best_branch()
            self._cache_off_branch(tree, branch, cache)
            if not branch or not np.isfinite(tree.utility[branch]).any():
                return f"no feasible view left after {captures} captures (iteration {it})"
            u_x = self._best_utility(tree, branch)
            self.iteration = it + 1
            if best_c is not None and u_x < best_c and len(cache):
                cached_tree = self.expand(session, f, obj, cache.positions)
                cached_branch = cached_tree.best_branch()
                self._cache_off_branch(cached_tree, cached_branch, cache)
                if cached_branch and np.isfinite(cached_tree.utility[cached_branch]).any():
                    u2 = self._best_utility(cached_tree, cached_branch)
                    if u2 > u_x:
                        tree, branch, u_x = cached_tree, cached_branch, u2
            self.best_utility = u_x
            if worst_c is not None and u_x <= worst_c:
                return (f"converged: best view U = {u_x:.4g} not above the worst cached node's "
                        f"{worst_c:.4g} after {captures} captures")
            if p.capture == "best_node":
                branch = [branch[int(np.argmax(tree.utility[branch]))]]
            obj, captured, refused = self.capture_branch(session, obj, tree, branch)
            if refused:
                cache.keep(~self.near_refused(cache.positions))
            self.n_failed_moves += refused
            captures += captured
            if captured == 0:
                failed_in_row += refused
                if failed_in_row >= p.max_failed_moves:
                    return f"{failed_in_row} moves in a row refused after {captures} captures"
                continue
            failed_in_row = 0
            m = max(1, round(p.cached_nodes * (1.0 - (it + 1) / p.max_iterations)))
            self._rescore(session, self.field(session, obj), obj, cache, m)
            best_c, worst_c = (float(cache.utility[0]), float(cache.utility[-1])) if len(cache) \
                else (None, None)
        return f"iteration limit ({p.max_iterations}) reached after {captures} captures"

    def figures(self) -> dict[str, float | int | str | None]:
        """Algorithm 1 so far: iterations, the utility of the last chosen view x*, refused moves."""
        return {"iteration": self.iteration, "best_utility": None if self.best_utility is None
                else round(self.best_utility, 6), "failed_moves": self.n_failed_moves}

    @staticmethod
    def _best_utility(tree: Tree, branch: list[int]) -> float:
        """Line 9: the utility of x*, the best node of the branch."""
        return float(np.max(tree.utility[branch]))


class LRNBVPlanner(RRTViewPlanner):
    """Algorithm 1 with all four gains (``lr-nbv``)."""

    section = "lrnbv"
    uses_density_and_visited = True


class NBVPlanner(RRTViewPlanner):
    """The NBV baseline: Algorithm 1 with the exploration and quality gains only (``nbv``)."""

    section = "nbv"
    uses_density_and_visited = False
