"""The configuration model of a cell: one YAML file under ``config/`` validated into ``CellConfig``.

Units are SI (m, s, rad) unless a field name says otherwise (``_deg``, ``_hz``, ``_pct``).
Safety-relevant values (speed limits, workspace) have no defaults: a cell file must state them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt, field_validator, model_validator
from pydantic_core import PydanticCustomError

from cell.line.config import LineConfig
from cell.line.result import feeder_part
from cell.packing.config import PackingConfig
from cell.perception.cloud import VoxelEdge
from cell.perception.filters import FilterParams
from cell.perception.occupancy import OccupancyParams
from cell.perception.registration import RegistrationParams
from cell.perception.segmentation import SegmentationParams
from cell.planning.lrnbv.config import HEUConfig, LRNBVConfig
from cell.planning.registry import PLANNERS
from cell.planning.vs.config import VSConfig, VSGlobalConfig, VSLocalConfig
from cell.safety.config import SafetyConfig
from drivers.arm.config import (
    LINE_INPUTS,
    LINE_NEEDS,
    LINE_OUTPUTS,
    ArmConfig,
    FlangeOffset,
    LinePinsConfig,
    ReplayArmConfig,
    SimArmConfig,
)
from drivers.config_base import (
    CELL_EXTENT_M,
    Bounds,
    CellCoordinate,
    CellDistance,
    CellSize,
    FiniteNumber,
    PositiveCount,
    PositiveNumber,
    StrictModel,
    Turn,
)
from drivers.depth.config import DepthConfig, ReplayConfig, SensorCoordinate
from drivers.errors import ServiceError
from drivers.sim.board import BoardConfig, SimBoardConfig
from drivers.sim.errors import SimErrorConfig, SimErrors
from drivers.sim.faults import SimFault
from drivers.transforms import T_from_xyz_rpy


class PoseConfig(StrictModel):
    """The pose of the sensor on the flange (T_flange_sensor): translation ``xyz_m`` [m] in the flange frame,
    each coordinate within :data:`~drivers.arm.config.TOOL_REACH_M` of the flange (the sensor is on the
    wrist), and extrinsic roll-pitch-yaw ``rpy_deg`` [deg], each within one turn."""

    xyz_m: tuple[FlangeOffset, FlangeOffset, FlangeOffset]
    rpy_deg: tuple[Turn, Turn, Turn] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        return T_from_xyz_rpy(self.xyz_m, np.deg2rad(self.rpy_deg))


class StationConfig(StrictModel):
    """Where objects are put: the station's centre ``xy_m`` on the table and the table top height
    ``table_z_m``, both in the robot base frame [m]: finite numbers, written as numbers. Where they lie
    against the table and the workspace is checked with the whole file (``cell.config.load``)."""

    xy_m: tuple[FiniteNumber, FiniteNumber]
    table_z_m: FiniteNumber = 0.0


class SimConfig(StrictModel):
    """The simulated world: the table's size and centre in the base frame [m], faults to inject on a
    schedule (``drivers.sim.faults``) to see the safety layer react, and ``true_mount``, the hand-eye
    transform T_flange_sensor the simulated sensor really has (None: the cell file's ``mount``), so that
    what a job believes (``mount``) can differ from the truth a calibration has to find; ``board``: the
    cell's calibration board (``calibration.board``) lying on the table (None: no board).

    ``error``: the calibration error a carefully calibrated real cell still has (hand-eye, kinematics,
    depth bias; sizes and reasons in ``drivers.sim.errors``), drawn per job from its seed, on unless
    ``exact`` is true (for the algorithm tests that need the sensor exactly where the job believes it is).
    A ``true_mount`` given replaces the drawn hand-eye error, and holds with ``exact`` too.

    Besides the scheduled faults, the simulated arm always faults when one of its bodies (the link
    capsules and ``safety.collision.tool``) touches the object as the sim placed it or this table: a
    protective stop (UR5e) or a reflex (Franka) naming the body and where (``drivers.sim.contact``)."""

    table_size_m: tuple[CellSize, CellSize] = (1.2, 1.0)
    table_center_xy_m: tuple[CellCoordinate, CellCoordinate] = (0.5, 0.0)
    faults: list[SimFault] = Field(default_factory=list)
    true_mount: PoseConfig | None = None
    board: SimBoardConfig | None = None
    exact: bool = False
    error: SimErrorConfig = SimErrorConfig()


class CalibrationConfig(StrictModel):
    """What ``cell calibrate`` uses: ``board``, the ChArUco board of the camera calibration (None: the
    cell has none)."""

    board: BoardConfig | None = None


class CropBoxConfig(StrictModel):
    """Axis-aligned box in the sensor frame [m], within the sensors' range; points outside are dropped
    (paper section II-A)."""

    x_m: tuple[SensorCoordinate, SensorCoordinate]
    y_m: tuple[SensorCoordinate, SensorCoordinate]
    z_m: tuple[SensorCoordinate, SensorCoordinate]

    @model_validator(mode="after")
    def _ordered(self) -> CropBoxConfig:
        for name in ("x_m", "y_m", "z_m"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"{name}: lower bound {lo} must be below upper bound {hi}")
        return self


class PerceptionConfig(StrictModel):
    """The per-frame pipeline (visual-servoing paper section II-A): crop box in the sensor frame, the
    voxel size [m] of filtering and accumulation (2.5 mm), the rate [Hz] at which frames are taken while
    the arm moves (sim time in sim mode; the paper ran at 0.7-1.3 Hz), and each stage's parameters.

    ``seen_obstacle_voxel_m``: the edge [m] of the grid on which every return standing on the table,
    before the crop box, is kept for the guard as an obstacle outside the object's ROI
    (``cell.perception.seen_obstacles``). 1 cm: the guard's own clearances are centimetres (the ROI's
    margin is 2 cm), a grid no finer than that adds at most a cell to every side of what was seen, and a
    part the size of the shipped objects is hundreds to a few thousand cells, whose mesh perception builds
    with every update."""

    crop_box: CropBoxConfig
    voxel_m: VoxelEdge = 0.0025
    seen_obstacle_voxel_m: VoxelEdge = 0.01
    rate_hz: float = Field(gt=0.0, le=60.0)
    filters: FilterParams = FilterParams()
    registration: RegistrationParams
    occupancy: OccupancyParams
    segmentation: SegmentationParams = SegmentationParams()


class RingConfig(StrictModel):
    """One ring of raster views: ``n_views`` views at ``elevation_deg`` above the table plane."""

    elevation_deg: float = Field(gt=0.0, le=90.0)
    n_views: PositiveInt


class RasterConfig(StrictModel):
    """The ``raster`` planner: predetermined rings of views around the station, each at ``standoff_m``
    from a point ``target_height_m`` above the table at the station, starting at ``start_azimuth_deg``
    (0 = looking along +x of the base frame)."""

    rings: list[RingConfig] = Field(min_length=1)
    target_height_m: CellDistance
    start_azimuth_deg: Turn = 180.0
    azimuth_span_deg: float = Field(default=360.0, gt=0.0, le=360.0)
    settle_s: float = Field(default=0.1, ge=0.0)


class PlannersConfig(StrictModel):
    """Per-planner parameters; a planner reads its own section. ``vs`` is shared by the three
    visual-servoing planners (``vs-local``, ``vs-global``, ``vs-hybrid``; Hybrid reads ``vs_local`` and
    ``vs_global``); their defaults are the visual-servoing paper's values."""

    raster: RasterConfig
    vs: VSConfig = VSConfig()
    vs_local: VSLocalConfig = VSLocalConfig()
    vs_global: VSGlobalConfig = VSGlobalConfig()
    # The packing paper's planners; ``nbv`` reads the same parameters and leaves G_d and G_v out.
    lrnbv: LRNBVConfig = LRNBVConfig()
    nbv: LRNBVConfig = LRNBVConfig()
    heu: HEUConfig = HEUConfig()


class ScanConfig(StrictModel):
    """A scan job: default planner (a name of :data:`cell.planning.registry.PLANNERS`), the distance Z*
    kept to the object [m] (paper eq. 2, 0.25 m), the control rate [Hz] at which motion is commanded and
    the sim clock steps, and the time budget [s]."""

    planner: str
    standoff_m: Annotated[float, Bounds(0.05, CELL_EXTENT_M, "m", "the sensor keeps 5 cm to 2 m from the "
                                        "object (clear of it, beyond the sensors' minimum range)")]
    control_rate_hz: float = Field(gt=0.0, le=1000.0)
    max_time_s: PositiveFloat

    @field_validator("planner")
    @classmethod
    def _registered(cls, name: str) -> str:
        # checked with the file: an unknown default passed config check and doctor, then every job failed
        if name not in PLANNERS:
            raise PydanticCustomError("planner", "'{name}' is no registered planner",
                                      {"name": name, "expected": ", ".join(PLANNERS)})
        return name


class RetentionConfig(StrictModel):
    """How long ``cell serve`` keeps ended jobs (their folders and store rows): ``days`` after they ended,
    and/or while the cell's job folders together stay under ``max_gb`` [GB, 1e9 bytes] (the oldest ended
    jobs go first). None: no limit of that kind. A running or queued job, and one marked ``keep``, is never
    deleted; anything else in the data dir's ``jobs/`` (a folder the store does not know) is neither
    counted nor deleted, but reported (``GET /api/v1/retention``, the log). The service prunes when it
    starts and every ``interval_h`` hours."""

    days: PositiveNumber | None = None
    max_gb: PositiveNumber | None = None
    interval_h: PositiveNumber = 1.0


class ServiceConfig(StrictModel):
    """``cell serve``: how many jobs may wait behind the running one (``queue_max``; beyond it a
    submission is refused), how long a stop request waits for the job's worker to confirm that the arm
    was commanded to stop [s], how long shutting down waits for a running job to stop and finish its
    folder [s], and the largest mesh an operator may upload [MB]. ``warm_worker``: keep the next job's
    worker process started, its libraries loaded, so that a job (a line's Start) reaches the arm without
    the second or so a new Python process takes to import them; it costs the memory of one idle worker.
    ``retention``: when ended jobs are deleted (:class:`RetentionConfig`; by default never). Numbers are
    written as numbers, as in the safety section (a quoted "1e9" is refused, not read)."""

    queue_max: PositiveCount = 16
    stop_confirm_timeout_s: PositiveNumber = 2.0
    shutdown_timeout_s: PositiveNumber = 20.0
    max_upload_mb: PositiveNumber = 50.0
    warm_worker: bool = True
    retention: RetentionConfig = RetentionConfig()


CELL_NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
"""A cell's name: 1-64 letters, digits, '.', '_', '-', from a letter or digit (the job store keeps 64
characters, and the name goes into file names)."""


def _shared_pins(pins: dict[str, int | None]) -> str | None:
    """The first two of ``pins`` (name: digital index, None: not wired) wired to the same index, in words;
    None when none are."""
    seen: dict[int, str] = {}
    for name, index in pins.items():
        if index is not None:
            if index in seen:
                return f"{seen[index]} and {name}"
            seen[index] = name
    return None


class CellConfig(StrictModel):
    """A whole cell: arm, sensor, its mount on the flange (hand-eye), station, perception, safety, scan,
    planners, the packing result (container catalogue), the service (``cell serve``) and the packing
    line's interface (``line``, None: no line).

    ``mode`` says which devices are real:

    - ``sim``: the simulated arm and a simulated sensor on the simulated clock (deterministic);
    - ``dry-run``: a hardware arm (``ur5e``, ``franka``) and a simulated sensor (``sim-...``) that renders
      the job's virtual object and the ``sim`` section's table from the pose the arm reports, on the wall
      clock. Every motion goes through the guard to the real controller; commissioning a cell starts
      this way, with no object on the table;
    - ``real``: a hardware arm and a hardware sensor;
    - ``replay``: a recorded job played back (``arm`` and ``sensor`` of type ``replay``, the same job
      folder) through this file's perception and a planner, on the simulated clock; nothing moves (see
      ``cell.jobs.replay``).
    """

    name: str = Field(pattern=CELL_NAME, description="the cell's name: the job store's key for its jobs and "
                                                     "its lease (one service per name on a store)")
    mode: Literal["sim", "dry-run", "real", "replay"]
    arm: ArmConfig
    sensor: DepthConfig
    mount: PoseConfig = Field(description="T_flange_sensor, the hand-eye transform")
    station: StationConfig
    sim: SimConfig = SimConfig()
    perception: PerceptionConfig
    safety: SafetyConfig
    scan: ScanConfig
    planners: PlannersConfig
    packing: PackingConfig = PackingConfig()
    service: ServiceConfig = ServiceConfig()
    line: LineConfig | None = None
    calibration: CalibrationConfig = CalibrationConfig()

    def true_mount_matrix(self, errors: SimErrors | None = None) -> np.ndarray:
        """T_flange_sensor (4x4) the simulated sensor renders from: ``sim.true_mount``, else ``mount`` moved
        by the drawn hand-eye error ``errors.T_mount_error`` (none when not given)."""
        if self.sim.true_mount is not None:
            return self.sim.true_mount.matrix()
        return self.mount.matrix() if errors is None else self.mount.matrix() @ errors.T_mount_error

    @model_validator(mode="after")
    def _consistent(self) -> CellConfig:
        # the servo law streams one twist per servo period, and the control loop takes at most one a tick
        vs = self.planners.vs
        if vs.servo_rate_hz > self.scan.control_rate_hz:
            raise ValueError(f"planners.vs.servo_rate_hz {vs.servo_rate_hz:g} exceeds scan.control_rate_hz "
                             f"{self.scan.control_rate_hz:g}")
        sim_arm = self.arm.type == "sim"
        sim_sensor = self.sensor.type.startswith("sim-")
        arm, sensor = self.arm, self.sensor
        if self.mode == "replay":
            if not (isinstance(arm, ReplayArmConfig) and isinstance(sensor, ReplayConfig)):
                raise ValueError("mode 'replay' needs arm.type 'replay' and sensor.type 'replay'")
            if Path(arm.job_dir) != Path(sensor.job_dir):
                raise ValueError(f"arm.job_dir ({arm.job_dir}) and sensor.job_dir ({sensor.job_dir}) "
                                 "must name the same recorded job")
            return self
        if isinstance(arm, ReplayArmConfig) or isinstance(sensor, ReplayConfig):
            raise ValueError("a replay arm or sensor plays a recorded job: it needs mode 'replay'")
        if self.mode == "sim" and not (sim_arm and sim_sensor):
            raise ValueError("mode 'sim' needs arm.type 'sim' and a 'sim-...' sensor type")
        if self.mode == "dry-run" and (sim_arm or not sim_sensor):
            raise ValueError("mode 'dry-run' needs a hardware arm type ('ur5e' or 'franka') and a 'sim-...' "
                             "sensor type")
        if self.mode == "real" and (sim_arm or sim_sensor):
            raise ValueError("mode 'real' needs a hardware arm type ('ur5e' or 'franka') and a hardware "
                             "sensor type (a simulated sensor with a hardware arm is mode 'dry-run')")
        if self.sim.board is not None and self.calibration.board is None:
            raise ValueError("sim.board lays the calibration board on the table: it needs calibration.board")
        if self.line is not None and self.line.dio is not None:
            if not isinstance(arm, LinePinsConfig) or arm.model != "ur5e":
                what = f"a simulated {arm.model}" if isinstance(arm, SimArmConfig) else f"a {arm.type} arm"
                raise ValueError("line.dio is the UR5e's digital-I/O handshake (a real or a simulated ur5e): "
                                 f"{what} has none")
            missing = [name for name, index in arm.line_pins(LINE_NEEDS).items() if index is None]
            if missing:
                raise ValueError(f"line.dio needs the arm's {', '.join(missing)}")
            for kind, names in (("input", LINE_INPUTS), ("output", LINE_OUTPUTS)):
                shared = _shared_pins(arm.line_pins(names))
                if shared:
                    raise ValueError(f"line.dio: the arm's {shared} are the same digital {kind}")
            if self.mode == "dry-run" and self.line.dio.part_id is not None:
                try:  # the simulated feeder's part: a malformed one would be refused at every trigger
                    feeder_part(self.line.dio.part_id)
                except ServiceError as exc:
                    raise ValueError(f"line.dio.part_id: {exc}") from None
        return self
