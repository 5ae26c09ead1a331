"""Parameters of the ``lr-nbv``, ``nbv`` and ``heu`` planners (LR-NBV paper, Table 1 and its open choices)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, PositiveFloat, PositiveInt, model_validator

from drivers.config_base import CellDistance, CellSize, StrictModel, Turn


class LRNBVConfig(StrictModel):
    """One RRT next-best-view planner (Algorithm 1). Defaults: Table 1 of the paper where it gives a value.

    Table 1: ``max_iterations`` (num.iterations, 300), ``samples_per_iteration`` (n, 50),
    ``cached_nodes`` (m at the first iteration, 50; it then decreases linearly to 1 at ``max_iterations``),
    ``visited_grid_m`` (the coarse grid of G_v, eq. 6, 0.18 m) and the weights of U:
    ``w_e`` 500, ``w_d`` 0.05, ``w_q`` 0.08, ``w_v`` 500. The map resolution (1 cm) is the occupancy map's,
    ``perception.occupancy.resolution_m``.

    Choices the paper leaves open:

    - ``density_radius_m``: r_d of eq. 4 [m], 2 map voxels;
    - ``ray_length_m``: a ray r(t) = o + t d of eqs. 2-4 runs over t in [0, 1] with |d| = ``ray_length_m``
      [m], sampled every map voxel (t_k spacing = resolution / ray_length);
    - ``roi_margin_m``: the ROI of eq. 2 is the object's axis-aligned box grown by this [m] on every side
      (but not below the table), so that the unknown space just around the object seen so far is worth
      exploring;
    - ``cache_threshold``: tau [utility units], nodes off the best branch above it are cached, and a
      node of the best branch is captured only while its re-scored utility stays above it (0: with the
      visited gain a node in a visited coarse cell scores about -w_v);
    - ``capture``: what captureData(B^i) (line 16) captures: ``branch``, the nodes of the best branch
      from the root outwards (each while its re-scored U stays above tau), or ``best_node``, x* alone;
    - ``rrt_step_m``: RRT extension step [m], about the diagonal of a visited-grid cell (0.31 m at
      0.18 m): with a shorter step a tree's first nodes stay in the cell just captured, where G_v = -1
      puts -w_v on every branch through them (eq. 1), so only short branches near the root stay
      positive and x* is poor (a 0.15 m step ended a horizontal_box scan after 9 captures at IoU
      0.76); node positions are drawn in the workspace box of the safety
      config within ``view_distance_m`` (min, max) [m] of the object centre and must pass
      ``sensor_pose_allowed``; nodes closer than ``object_clearance_m`` [m] to the object's box are dropped;
    - ``look_target_spread``: a node's orientation is the best of 9 look-at directions: the object box
      centre and its 8 corners pulled towards the centre to this fraction (0: only the centre);
    - ``settle_s`` [s] waited after a move before a capture; ``max_failed_moves`` moves in a row that the
      session refuses (unreachable, collision, barrier) end the scan; nodes within ``refused_radius_m``
      [m] of a refused position are dropped from later trees and from the cache;
    - ``rgbd_rays_per_side``: rays across a pinhole camera's wider side (the ToF casts one per zone);
    - ``exploration_weight``: W of eq. 3, ``entropy`` (the paper's, Selin et al.'s normalised occupancy
      entropy) or ``observation`` (that entropy capped by the information one more observation gives,
      which falls like 1 / n with the n scans that updated the voxel, so that surface voxels seen often
      and still ambiguous stop drawing views; a departure from the paper, ``cell.planning.lrnbv.utility``);
    - ``search_heights_m`` [m] above the table from which the station is looked at, in turn, while the
      first captures show no object (Algorithm 1 needs an initial acquisition of it); then the poses of
      the cell's ``heu`` ellipse.
    """

    max_iterations: PositiveInt = 300
    samples_per_iteration: PositiveInt = 50
    cached_nodes: PositiveInt = 50
    visited_grid_m: CellSize = 0.18
    w_e: PositiveFloat = 500.0
    w_d: PositiveFloat = 0.05
    w_q: PositiveFloat = 0.08
    w_v: PositiveFloat = 500.0
    density_radius_m: CellSize = 0.02
    ray_length_m: CellSize = 1.0
    roi_margin_m: CellDistance = 0.05
    cache_threshold: float = 0.0
    """[utility units] tau: the utility above which nodes are cached and branch nodes captured."""
    capture: Literal["branch", "best_node"] = "branch"
    rrt_step_m: CellSize = 0.3
    view_distance_m: tuple[CellSize, CellSize] = (0.2, 0.6)
    object_clearance_m: CellDistance = 0.08
    look_target_spread: float = Field(default=0.5, ge=0.0, le=1.0)
    """[1] the fraction towards the box centre at which the look-at corners are taken (0: only the centre)."""
    rgbd_rays_per_side: PositiveInt = 16
    settle_s: float = Field(default=0.1, ge=0.0)
    max_failed_moves: PositiveInt = 10
    refused_radius_m: CellDistance = 0.1
    search_heights_m: tuple[CellSize, ...] = (0.3, 0.22)
    exploration_weight: Literal["entropy", "observation"] = "observation"

    @model_validator(mode="after")
    def _ordered(self) -> LRNBVConfig:
        lo, hi = self.view_distance_m
        if not lo < hi:
            raise ValueError(f"view_distance_m: minimum {lo} must be below maximum {hi}")
        return self


class HEUConfig(StrictModel):
    """The ``heu`` baseline (LR-NBV paper section 4): ``n_poses`` (13) evenly spaced sensor positions on a
    horizontal ellipse centred on the object's position (the configured station), semi-axes
    ``semi_axes_m`` (along base x, y) [m], ``height_m`` [m] above the table, each looking at the point
    ``target_height_m`` [m] above the table at the station; ``start_angle_deg`` [deg] of the first pose
    (0 = +x of the base frame); ``settle_s`` [s] waited after each move before the capture."""

    n_poses: PositiveInt = 13
    semi_axes_m: tuple[CellSize, CellSize] = (0.3, 0.3)
    height_m: CellSize = 0.35
    target_height_m: CellDistance = 0.05
    start_angle_deg: Turn = 180.0
    settle_s: float = Field(default=0.1, ge=0.0)
