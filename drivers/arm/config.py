"""Configuration of each arm backend, selected by ``type:`` (a pydantic discriminated union)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, PositiveFloat

from drivers.config_base import Bounds, Number, StrictModel

RobotModelName = Literal["panda", "ur5e"]


DIGITAL_PINS = 8
"""How many standard digital inputs, and as many outputs, a UR5e's control box has (DI0-DI7, DO0-DO7)."""
DigitalIndex = Annotated[int, Field(ge=0, le=DIGITAL_PINS - 1)]

LINE_INPUTS = ("trigger_input", "reset_input")
"""The standard digital inputs of a UR5e a packing line may wire (:class:`UR5eArmConfig`'s fields of these
names; ``cell.line.dio`` is the handshake): a rising trigger starts a scan, a rising reset resets the line.
The code's one list of them; the docs name them."""
LINE_OUTPUTS = ("busy_output", "done_output", "ready_output", "fault_output")
"""The standard digital outputs of a UR5e a packing line may wire (fields of these names), as
``cell.line.dio.output_levels`` drives them: busy in Execute, done in Complete, ready in Idle in
Production, fault after a stop the line did not command."""
LINE_NEEDS = ("trigger_input", "busy_output", "done_output")
"""The pins of :data:`LINE_INPUTS` and :data:`LINE_OUTPUTS` that ``line.dio`` needs wired; the others are
optional."""

TOOL_REACH_M = 0.5
"""How far [m] from the flange, along each axis of the flange frame, anything the wrist carries may lie:
the TCP, the sensor (its mount), the payload's centre of mass. This cell's wrist tool is a depth sensor on
a bracket, a few centimetres; a tool reaching further than 0.5 m is not this cell's (it would be most of
the arm's own 0.85 m reach), and 40 (millimetres written in a metres field) is refused."""

FlangeOffset = Annotated[float, Bounds(-TOOL_REACH_M, TOOL_REACH_M, "m",
                                       f"the wrist tool lies within {TOOL_REACH_M:g} m of the flange")]
"""[m] one coordinate of a point of the wrist tool in the flange frame (:data:`TOOL_REACH_M`)."""

ROTATION_VECTOR_MAX_RAD = 6.2832
"""The largest component [rad] of a rotation vector (axis-angle) in a cell file: 2 pi, rounded up. A
rotation is a turn of at most pi about its axis (UR's pendant writes it so), at most 2 pi the long way
round; 90 is degrees written in a radians field."""

RotationVectorComponent = Annotated[float, Bounds(-ROTATION_VECTOR_MAX_RAD, ROTATION_VECTOR_MAX_RAD, "rad",
                                                  "a rotation vector's components lie within +-2 pi rad")]
"""[rad] one component of a rotation vector (:data:`ROTATION_VECTOR_MAX_RAD`)."""


class PayloadConfig(StrictModel):
    """What the flange carries (sensor, bracket, cables): mass [kg] and centre of mass in the flange frame
    [m]. The controller uses it for gravity compensation and collision detection, so it has no default."""

    mass_kg: float = Field(ge=0.0, le=5.0)
    cog_m: tuple[FlangeOffset, FlangeOffset, FlangeOffset]
    """[m] the centre of mass in the flange frame: within the tool, so within :data:`TOOL_REACH_M` of the
    flange on each axis."""


class LinePinsConfig(StrictModel):
    """The standard digital inputs and outputs a packing line's handshake (``cell.line.dio``) is wired to
    (:data:`LINE_INPUTS`, :data:`LINE_OUTPUTS`; ``None``: not wired): a UR5e's, and a simulated UR5e's,
    which a sim cell offers an integrator to try the handshake on (``cell line dio``)."""

    busy_output: DigitalIndex | None = None
    done_output: DigitalIndex | None = None
    trigger_input: DigitalIndex | None = None
    reset_input: DigitalIndex | None = None
    ready_output: DigitalIndex | None = None
    fault_output: DigitalIndex | None = None

    def line_pins(self, names: tuple[str, ...]) -> dict[str, int | None]:
        """The digital index each pin of ``names`` (of :data:`LINE_INPUTS`, :data:`LINE_OUTPUTS`) is wired
        to, by name; None: not wired."""
        return {name: getattr(self, name) for name in names}


class SimArmConfig(LinePinsConfig):
    """The simulated arm: integrates commanded twists through the model's differential IK. A simulated
    ``ur5e`` has the UR5e's eight standard digital inputs and outputs for the line's handshake
    (``line.dio``, the pins as a UR5e's: ``trigger_input``, ``busy_output``, ...): the service holds them,
    its outputs driven by the handshake and its inputs set over REST (``PUT /api/v1/line/dio/inputs/NAME``,
    ``cell line dio set``), where a real UR5e's are the PLC's wires."""

    type: Literal["sim"]
    model: RobotModelName
    home_joints_rad: list[float] | None = None


class UR5eArmConfig(LinePinsConfig):
    """A UR5e controller reached through ur-rtde (hardware backend; see :mod:`drivers.arm.ur5e`).

    - ``tcp_offset``: the TCP in the flange frame as a UR pose (x, y, z [m], rx, ry, rz [rad, axis-angle]),
      sent to the controller with ``setTcp``; the driver still reports and commands the flange. x, y, z lie
      within :data:`TOOL_REACH_M` of the flange, each rotation component within +-2 pi rad.
    - ``max_linear_mps`` / ``max_angular_rps``: the driver's own ceiling on every twist it sends (a second
      line behind the safety guard's limits); ``acceleration_mps2`` the speedL acceleration and
      ``stop_deceleration_mps2`` the speedStop / stopL deceleration.
    - ``rtde_frequency_hz``: RTDE data rate (the controller runs at 500 Hz); ``servo_rate_hz``: the rate
      at which trajectory samples are streamed with servoJ; ``servo_lookahead_s`` and ``servo_gain`` are
      servoJ's smoothing parameters (UR ranges 0.03-0.2 s and 100-2000); a trajectory's last sample is
      held until every joint is within ``settle_tolerance_rad`` of it, for at most ``settle_timeout_s``.
    - ``watchdog_min_hz``: the RTDE watchdog armed while the arm moves: the control script stops the arm
      when no command or kick arrives for 1 / ``watchdog_min_hz`` seconds.
    - ``busy_output`` / ``done_output``: standard digital outputs driven for a packing line, and
      ``trigger_input``: the standard digital input a line raises to start a scan (``None``: not wired);
      optionally ``reset_input`` (a rising edge resets the line, or clears it when aborted),
      ``ready_output`` (high when a trigger would start a scan) and ``fault_output`` (high when the line
      stopped for a fault or holds): the handshake is ``cell.line.dio``'s.
    - ``connect_timeout_s``: how long to wait for each controller port before giving up.
    """

    type: Literal["ur5e"]
    model: Literal["ur5e"] = "ur5e"
    host: str
    home_joints_rad: list[float] | None = None
    connect_timeout_s: PositiveFloat = 5.0
    tcp_offset: tuple[FlangeOffset, FlangeOffset, FlangeOffset,
                      RotationVectorComponent, RotationVectorComponent, RotationVectorComponent]
    """[m, m, m, rad, rad, rad] the TCP in the flange frame as a UR pose: x, y, z (each within 0.5 m of the
    flange), then the rotation vector (axis-angle)."""
    payload: PayloadConfig
    max_linear_mps: Number = Field(gt=0.0, le=1.0)
    max_angular_rps: Number = Field(gt=0.0, le=3.2)
    acceleration_mps2: Number = Field(gt=0.0, le=5.0)
    stop_deceleration_mps2: Number = Field(gt=0.0, le=10.0)
    rtde_frequency_hz: float = Field(default=500.0, gt=0.0, le=500.0)
    servo_rate_hz: float = Field(default=125.0, gt=0.0, le=500.0)
    servo_lookahead_s: float = Field(default=0.1, ge=0.03, le=0.2)
    servo_gain: float = Field(default=300.0, ge=100.0, le=2000.0)
    """[1] servoJ's proportional gain (UR's range 100-2000)."""
    settle_tolerance_rad: float = Field(default=1e-3, gt=0.0, le=0.05)
    settle_timeout_s: float = Field(default=2.0, gt=0.0, le=10.0)
    watchdog_min_hz: Number = Field(gt=0.0, le=500.0)


class FrankaArmConfig(StrictModel):
    """A Franka arm reached through franky-control (hardware backend; see :mod:`drivers.arm.franka`).

    - ``relative_dynamics_factor``: share (0, 1] of the robot's velocity, acceleration and jerk limits
      that every motion may use.
    - ``velocity_hold_s``: each commanded twist is a Cartesian velocity motion that lasts this long
      unless renewed; the control loop renews it at its rate, so the arm stops within this time when the
      loop stops.
    - ``max_linear_mps`` / ``max_angular_rps``: the driver's own ceiling on every twist it sends.
    - ``torque_threshold_nm`` / ``force_threshold_n``: the collision reflex thresholds.
    - ``realtime``: ``enforce`` refuses to connect without a realtime kernel (libfranka's default);
      ``ignore`` is for simulators and non-realtime test machines.
    """

    type: Literal["franka"]
    model: Literal["panda"] = "panda"
    host: str
    home_joints_rad: list[float] | None = None
    connect_timeout_s: PositiveFloat = 5.0
    relative_dynamics_factor: Number = Field(gt=0.0, le=1.0)
    """[1] the share of the robot's velocity, acceleration and jerk limits that every motion may use."""
    velocity_hold_s: float = Field(gt=0.0, le=0.5)
    max_linear_mps: Number = Field(gt=0.0, le=1.7)
    max_angular_rps: Number = Field(gt=0.0, le=2.5)
    payload: PayloadConfig
    torque_threshold_nm: Number = Field(gt=0.0, le=100.0)
    force_threshold_n: Number = Field(gt=0.0, le=100.0)
    realtime: Literal["enforce", "ignore"] = "enforce"


class ReplayArmConfig(StrictModel):
    """A recorded job's poses played back as a read-only arm (``mode: replay``; see
    :mod:`drivers.arm.replay`): ``job_dir`` is the job folder and ``model`` the robot that recorded it.
    It has no home joints: it cannot move."""

    type: Literal["replay"]
    model: RobotModelName
    job_dir: str
    home_joints_rad: None = None


ArmConfig = Annotated[SimArmConfig | UR5eArmConfig | FrankaArmConfig | ReplayArmConfig,
                      Field(discriminator="type")]
