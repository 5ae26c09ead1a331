"""Parameters of the visual-servoing planners (``planners.vs``, ``planners.vs_local``, ``planners.vs_global``
and ``planners.vs_hybrid`` in a cell file). Defaults are the visual-servoing paper's values; where the
paper is silent the docstring says what was chosen and why."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, PositiveFloat, PositiveInt, model_validator

from cell.perception.entropy_form import EntropyForm
from drivers.config_base import Bounds, CellDistance, CellSize, StrictModel, Turn


class ObjectiveConfig(StrictModel):
    """The ray grid of the entropy objective (eq. 9): ``rays_per_side`` x ``rays_per_side`` rays (23 x 23,
    K = 529) spread evenly in angle over a square field of view of ``fov_deg`` (30 deg). With
    ``use_sensor_fov`` and a multizone time-of-flight sensor (``sim-tof``, ``vl53l8cx``), the grid spans
    the sensor's own field of view instead (45 deg for the VL53L8CX), still ``rays_per_side`` per side:
    the ToF's field of view and the ray count from config. One ray per zone (8 x 8) made f piecewise
    constant at the scale of a servo step on the ToF cell's 1 cm map, and its central differences (eq.
    5-6) noise: ||g|| 0 to 400, changing sign from one evaluation to the next, and a VS-Local bunny scan
    dithering in place for its whole 180 s budget (6 m of path within a few centimetres, 5 % coverage);
    with 23 x 23 rays over the same 45 deg it converged at 31 s with 9.3 % (``rays_per_side: 8`` casts
    one ray per zone again).

    ``voxel_entropy``: the uncertainty H a voxel adds along a ray. ``shannon`` is eq. 8 as written,
    H(p). ``residual`` (the default, a departure) is what observation can still remove: H(p) - H(c),
    c the map's clamping bound on p's side (OctoMap clamps p to [0.12, 0.97], so a voxel seen free many
    times keeps H(0.12) = 0.37 nats, more than half of an unknown voxel's ln 2). With ``shannon`` that
    floor dominates f once the free space around the object is known (98 % of f at the end of a bunny
    scan): f then measures the length of free path through the ROI rather than what a view would reveal,
    and VS-Local settles where that path is longest instead of moving on.

    ``entropy``: ``paper`` takes each voxel's H as ``voxel_entropy`` gives it; ``observation_aware`` (the
    default, a departure from eq. 8) weights it by the information one more observation of the voxel can
    still give, I(h, m) / I(0, 0) of its hit and miss counts under a Beta-Bernoulli model (1 for an
    unseen voxel, falling like 1 / n for one seen n times; ``cell.planning.vs.objective``), so that
    voxels the views keep disagreeing on (a surface crossing them at a slant, a calibration error) stop
    drawing the camera and holding f above the termination's floor, and unseen space does not; and a voxel
    hit only from the other side of a ray counts for it as one not hit yet (``OccupancyMap.hit_sides``: the
    two faces of a wall thinner than a voxel share voxels; ``cell.planning.vs.objective``). The same form is
    the one in which every job reports H_ROI (eq. 12: result.json's ``perception.h_roi`` with its
    ``h_roi_entropy``, progress, the log), whatever its planner (``lr-nbv``, ``nbv`` and ``heu`` too), and
    the one the servo planners' termination judges (``ServoScanPlanner.entropy_settled``).

    ``roi_margin_m`` [m]: the rays are clipped to the object's ROI box (the box of every ROI of the scan so
    far, ``cell.perception.segmentation.ObjectExtent``) grown by this much sideways and upwards, and downwards
    to one voxel above the table the object stands on (``station.table_z_m``: the voxels the table's surface
    lies in hold its hits and range noise, not the object). The bottom is a departure too: the segmented box
    ends at the lowest voxel of the largest cluster, and whatever lies between it and the table can only be
    the object. Down to the table itself, Table I's banana (seeds 1, 2) lost 17-20 points of coverage (79.7 /
    79.9 % online against 98.4 / 86.3 % with the segmented box); one voxel above it, 88.2 / 85.7 %, the held-
    out washer, torus and cup keeping their gains (94.3, 98.4, 96.2 %). Segmentation drops the voxels within
    ``plane_distance_m`` (6 mm) of the table, half of a 12 mm washer, and a mushroom's stem, whose top its 2
    cm overhang hides, is a cluster of its own: their extents ended 12 mm and 6 cm above the table, and the
    unseen sides below never counted in f (VS-Local washer, seed 0: 76.2 -> 83.2 % coverage).
    The paper clips to the box itself; but that box ends at the seen extent of the
    object, and the space just beyond an edge seen from one side never counts: with no margin a VS-Local cube
    scan (RGB-D cell, seed 0) stopped on top after 18 s with 63 % coverage, its rays seeing only the known top
    face. The margin is not free, though. Its known-free voxels are clamped at p = 0.12, and eq. 7 lets a ray
    through each with probability 0.88 only, so a shell of them in front of the object weakens what lies
    behind by an amount that depends on where the ray crosses the box's faces, and its own unseen parts (the
    table's shadow beside the object) draw the camera long after the object's surface is known: on the maps of
    the last third of a VS-Local teapot scan, ||g|| was 6-50 with 3 cm and 1-3 with 1 cm (``f_eps_nats``
    0.03). The default, 3 cm, is what the ToF cells (1 cm voxels) were measured with; the RGB-D cells (5 mm
    voxels) use 1 cm, two voxels: on Table I's objects (VS-Local, seed 0, ``f_eps_nats`` 0.03) 3 cm gave 8 of
    8 objects at the paper's coverage in 51.2 s on average, 1 cm 8 of 8 in 45.2 s, 0 cm 7 of 8 (the cube as
    above) in 36.9 s (``benchmarks/vs_table.py``); on ten shapes and placements outside Table I
    (``cell eval heldout``) the mean coverage rose from 82.4 to 88.3 % at 1 cm, the mean scan time
    from 49.8 to 51.4 s.
    """

    rays_per_side: PositiveInt = 23
    fov_deg: Annotated[float, Bounds(5.0, 120.0, "deg", "the rays span a field of view a depth sensor "
                                     "has: 45-60 deg for the ToF sensors, up to about 120 deg for RGB-D "
                                     "cameras")] = 30.0
    """[deg] the square field of view of the rays when ``use_sensor_fov`` is false."""
    use_sensor_fov: bool = True
    voxel_entropy: Literal["shannon", "residual"] = "residual"
    entropy: EntropyForm = "observation_aware"
    roi_margin_m: CellDistance = 0.03


class ServoConfig(StrictModel):
    """The dual-task law (eq. 1-3) and ViSP's adaptive gain lambda_e(x) = (l0 - linf) exp(-l0' x /
    (l0 - linf)) + linf of the primary task [1/s] (``lambda_0`` 2, ``lambda_inf`` 0.4, ``lambda_0_slope``
    30); ``lambda_g`` (0.33) the flat gain of the secondary task; the secondary task starts once
    ||e|| < ``e_converged_m`` (5 mm) and stays on afterwards.

    ``lambda_g`` sets the exploration speed, though not as its value suggests. g (||g|| <= 1, a direction:
    section II-B 2) reaches the twist through the primary task's null-space projector, whose 6-vector
    mixes metres and radians: of a unit sideways g it keeps Z*^2 / (1 + Z*^2) as translation (5.9 % at
    Z* = 0.25 m, with Z* in metres; the rest becomes the turn that keeps the object centred), so the
    paper's 0.33 moves the camera at 1.9 cm/s at most. The RGB-D cells use 0.85, 5 cm/s: the map eq. 9
    reads is rebuilt once per perception period (1 s) and eq. 5-6 compare views delta = 5 cm apart, so at
    delta per perception period the camera never moves further between two maps than the scale on which
    the gradient says where to go. Table I, VS-Local, seed 0, calibration error on: mean scan time 34.4 s
    against 53.4 s, coverage of the upright-view limit (``cell.evaluation.limit`` before the roll was free,
    up to 3 points lower) at least 0.95 on 6 of 8 objects against 4 (banana 1.01 against
    0.82, dragon 0.99 against 0.945; ``cell eval vs-table``): a slow camera used its time on views that
    one map apart showed nearly the same thing, and converged before it had been round the object. By
    the same rule VS-Local crosses views it has used up, led by a longer arc of k deltas, at k deltas per
    period (``cell.planning.vs.local``), up to the cell's TCP speed limits."""

    lambda_0: PositiveFloat = 2.0
    """[1/s] the primary task's adaptive gain at ||e|| = 0."""
    lambda_inf: PositiveFloat = 0.4
    """[1/s] the primary task's adaptive gain as ||e|| grows large."""
    lambda_0_slope: PositiveFloat = 30.0
    lambda_g: float = Field(default=0.33, ge=0.0)
    e_converged_m: CellSize = 0.005

    @model_validator(mode="after")
    def _gain_decreasing(self) -> ServoConfig:
        if not self.lambda_0 > self.lambda_inf:
            raise ValueError(f"lambda_0 {self.lambda_0} must exceed lambda_inf {self.lambda_inf}")
        return self


class StartViewConfig(StrictModel):
    """Where a servo scan starts (paper III-B: "approximately the same sideways view of the object"): at
    ``scan.standoff_m`` from a point ``target_height_m`` [m] above the station on the table, at
    ``elevation_deg`` above the table plane and ``azimuth_deg`` of the camera position about +z from the
    base's +x axis (0: beyond the station, looking back at the robot; 270: on the -y side, a sideways view
    that both the Panda and the UR5e reach)."""

    target_height_m: CellDistance = 0.06
    elevation_deg: float = Field(default=30.0, gt=0.0, le=90.0)
    azimuth_deg: Turn = 270.0


class VSConfig(StrictModel):
    """What the three servo strategies share. ``servo_rate_hz`` (50; paper 30-80 Hz Local, 40-125 Hz
    Global) is the rate of job time at which the law is evaluated and a new twist streamed; it must not
    exceed ``scan.control_rate_hz``. ``barrier_activation_m`` [m]: the exploration direction loses its
    component into a barrier plane closer than this (paper Fig. 3; the paper gives no figure, 2 cm is
    about one servo second of sliding at the speeds reached). ``centroid_tau_s`` [s]: time constant of
    the centroid low-pass filter (paper II-A; not given there, 0.5 s is half a perception period).
    ``h_roi_window`` (10) and ``h_roi_std`` (0.001): the H_ROI termination of Global and Hybrid (eq. 12,
    section II-D): stop when the standard deviation of the last ``h_roi_window`` values is below it.
    ``first_object_timeout_s`` [s]: a scan whose start view shows no object for this long fails.
    ``joint_activation_rad`` [rad]: the secondary task g loses its component that would move a joint
    closer than this to its position margin further towards it, so that the camera slides along a joint
    limit as along a barrier plane instead of pressing into it (not in the paper, whose barrier planes
    were placed to keep the Panda from its limits; 0.15 rad is about two seconds of joint travel at the
    exploration speeds).
    ``singular_value_activation``: likewise, g loses its component that would lower the smallest
    singular value of the arm's Jacobian (``RobotModel.min_singular_value``) once it is below this, so
    that the camera slides along the edge of the arm's reach instead of servoing into it (not in the
    paper, whose barrier plane at the Panda's maximum reach did this for its one placement, Fig. 3;
    beyond the edge the differential IK cannot hold the primary task: a teapot scan's arm reached a
    singular value of 0.001 and lost the object by 3 to 6 cm for 15 s). 0.06 is three times the IK's
    damping, where it still realizes 90 % of a twist along the weakest direction.
    ``backoff_s`` [s]: after the guard refused a streamed twist (a collision predicted ahead), the
    arm retraces its joint path of this long before the refusal, then the camera carries on with the
    refused secondary direction blocked within ``refusal_radius_m`` [m] of where it was refused
    (``ServoScanPlanner``)."""

    servo_rate_hz: float = Field(default=50.0, gt=0.0, le=1000.0)
    objective: ObjectiveConfig = ObjectiveConfig()
    servo: ServoConfig = ServoConfig()
    start: StartViewConfig = StartViewConfig()
    barrier_activation_m: CellSize = 0.02
    centroid_tau_s: float = Field(default=0.5, ge=0.0)
    h_roi_window: int = Field(default=10, ge=2)
    h_roi_std: PositiveFloat = 0.001
    """[nats] the standard deviation of the last ``h_roi_window`` H_ROI values below which Global and Hybrid
    stop."""
    first_object_timeout_s: PositiveFloat = 5.0
    joint_activation_rad: Annotated[float, Bounds(0.001, 3.1416, "rad", "a distance to a joint limit is "
                                                  "under half a turn")] = 0.15
    singular_value_activation: float = Field(default=0.06, ge=0.0)
    backoff_s: PositiveFloat = 1.0
    refusal_radius_m: CellSize = 0.05


class VSLocalConfig(StrictModel):
    """VS-Local (eq. 4-6): central differences over ``delta_m`` (5 cm) along the camera's x and y, the
    gradient divided by f(r) + ``f_eps_nats`` and scaled by ``alpha`` [m], its norm clipped to ``g_max``
    (1); the scan ends when ||g|| < ``g_max`` (before clipping) in more than ``converged_fraction``
    (80 %) of the last ``window`` (200) servo evaluations; a camera that stayed within ``delta_m`` of its
    mean position over them has its difference over delta judged flat until a longer arc has led it that
    arc's length away (a departure). The relative gradient and ``alpha`` = 1 m depart from the paper's 1e-4
    on an unstated scale of f: see ``cell.planning.vs.local``.

    ``reach_deg`` [deg]: where ||g|| over ``delta_m`` is below ``g_max``, the camera heads for the view, among
    the displacements of eq. 5-6 (with their diagonals, and round the vertical at the camera's height) over
    arcs of the viewing sphere of 2, 3, ... times ``delta_m``'s up to this angle, whose f exceeds f(r) most
    per metre of arc, before the evaluation counts towards convergence (a
    departure; 0, the default, is the paper's single delta; the RGB-D cells
    use 175, a half turn: a camera that has used up the information around it otherwise ends on a plateau,
    not at a maximum, see ``cell.planning.vs.local``). While an arc of k ``delta_m``'s leads, the camera
    moves at k times the exploration speed (``ServoConfig``), up to the cell's TCP speed limits: it is
    crossing views it has used up. VS-Hybrid always uses the single delta."""

    delta_m: CellSize = 0.05
    reach_deg: float = Field(default=0.0, ge=0.0, lt=180.0)
    alpha: PositiveFloat = 1.0
    """[m] the scale of the relative gradient."""
    f_eps_nats: PositiveFloat = 0.03
    g_max: PositiveFloat = 1.0
    """[1] the largest norm of g, and the norm below which an evaluation counts towards convergence."""
    window: PositiveInt = 200
    converged_fraction: float = Field(default=0.8, gt=0.0, lt=1.0)
    """[1] the share of the last ``window`` evaluations with ||g|| < ``g_max`` that ends the scan."""


class VSGlobalConfig(StrictModel):
    """VS-Global (eq. 10-11): ``n_candidates`` (5000) poses on the sphere of radius Z* around the centroid,
    each looking at it; g is the unit tangent direction to the best one, its length decaying linearly to
    zero within ``slow_radius_m`` (10 cm) of the goal; the goal counts as reached (and a new one is
    sampled) within ``arrival_m`` [m] (not given in the paper: 5 cm, where g has halved; the linear decay
    makes the approach exponential, about 5 s per halving at lambda_g = 0.33, and H_ROI would settle
    during a 1 cm approach before the goal's view is reached), or given up once the camera got less than
    ``stall_progress_m`` [m] closer to it along the sphere within the last ``stall_time_s`` [s] (not in
    the paper: a goal
    the barrier projection cannot reach would otherwise hold the scan forever; 1 cm in 3 s, where the
    approach covers 6 cm in 3 s at full speed and 3 cm at the arrival distance). Candidates are drawn
    from the job's planner generator (``ScanSession.rng``), so a scan is repeatable for a given job seed.
    ``reachability_checks``: the goal is the best candidate the arm can servo to, among this many best
    (0: the best allowed candidate, unchecked): inverse kinematics follows the arc from the camera to it
    every ``path_step_m`` [m] within the joint margins, free of collision and without a change of
    configuration (not in the paper; 3 cm, about 7 deg of arc, keeps a joint's step between poses well
    below a flip; see ``cell.planning.vs.goals``)."""

    n_candidates: PositiveInt = 5000
    slow_radius_m: CellSize = 0.10
    arrival_m: CellSize = 0.05
    stall_time_s: PositiveFloat = 3.0
    stall_progress_m: CellSize = 0.01
    reachability_checks: int = Field(default=50, ge=0)
    path_step_m: CellSize = 0.03

