"""The simulated arm's contact with the true object and the table: it faults as a real arm's collision
detection would (a UR5e's protective stop, a Franka's reflex), saying what touched what where, and stops;
a whole scan that drives the arm into a part it has not seen ends with that arm fault."""

from __future__ import annotations

import json

import fcl
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.safety.collision import CollisionWorld
from drivers.arm.base import ArmMode, MotionToken
from drivers.arm.config import SimArmConfig
from drivers.arm.sim import SimArm
from drivers.clock import SimClock
from drivers.errors import RobotFault
from drivers.fcl_bodies import fcl_transform, mesh_bvh
from drivers.robots import get_robot_model
from drivers.sim.contact import SimContact
from drivers.sim.objects import ObjectMesh
from drivers.sim.scene import SimScene
from drivers.transforms import make_T

from .conftest import FRANKA, UR5E

DT = 0.01  # the cells' control period [s]
SPEED = np.array([0.0, 0.0, -0.1, 0.0, 0.0, 0.0])  # the flange straight down at 10 cm/s (base frame)


def _block(size_m: float) -> ObjectMesh:
    """A cube of edge ``size_m`` [m] in the object frame (centred on x = y = 0, base at z = 0)."""
    box = trimesh.creation.box([size_m] * 3)
    return ObjectMesh("block", np.asarray(box.vertices) + np.array([0.0, 0.0, size_m / 2.0]),
                      np.asarray(box.faces, dtype=np.int32))


def _lowest(T_base_body: np.ndarray, bounds: np.ndarray) -> float:
    """The height [m, base frame] of the lowest corner of a body's box ``bounds`` (2, 3) at its pose."""
    corners = np.array([[x, y, z] for x in bounds[:, 0] for y in bounds[:, 1] for z in bounds[:, 2]])
    return float(np.min(corners @ T_base_body[2, :3] + T_base_body[2, 3]))


def _cell(config_path, *, obj: ObjectMesh | None, below_tool_m: float, table_size_m: float
          ) -> tuple[SimArm, SimClock, float]:
    """A connected sim arm of the cell at home, watched for contact with a scene whose table (or, with
    ``obj``, the object standing on it) tops ``below_tool_m`` [m] under the lowest corner of the boxes of
    the arm's tool and last link, centred under the flange; the table is ``table_size_m`` [m] wide.
    Returns the arm, its clock and that top's height [m, base frame]."""
    cfg = load_config(config_path)
    model = get_robot_model(cfg.arm.model)
    clock = SimClock()
    assert isinstance(cfg.arm, SimArmConfig)
    arm = SimArm(cfg.arm, model, clock)
    bodies = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m).arm_bodies()
    frames = arm.true_frames()
    # the tool and the last link (carried by the flange, the last body's frame, and the frame before it)
    flange = max(b.frame for b in bodies)
    top = min(_lowest(frames[b.frame] @ b.T_frame_body, b.bounds) for b in bodies
              if b.frame >= flange - 1) - below_tool_m
    table_z = top - (0.0 if obj is None else float(np.ptp(obj.vertices[:, 2])))
    x, y = frames[-1][:2, 3]
    scene = SimScene(obj, make_T(np.eye(3), np.array([x, y, table_z])), table_z=table_z,
                     table_center_xy=(x, y), table_size_xy=(table_size_m, table_size_m))
    SimContact(clock, arm, scene, bodies)
    arm.connect()
    return arm, clock, top


def _lower_until_fault(arm: SimArm, clock: SimClock, seconds: float) -> MotionToken:
    """Stream the flange down until the arm faults (or ``seconds`` [s] of sim time pass); returns the
    motion token."""
    token = arm.claim_motion()
    arm.command_twist(SPEED, token)
    while clock.now() < seconds and arm.fault is None:
        clock.sleep(DT)
    return token


def _where(fault: str) -> np.ndarray:
    """The contact point [m, base frame] a contact fault names."""
    return np.array([float(v) for v in fault.split(" at (")[1].split(")")[0].split(", ")])


@pytest.mark.parametrize(("config_path", "kind"), [(UR5E, "protective stop"), (FRANKA, "reflex")])
def test_the_arm_driven_into_a_small_object_faults_with_the_contact_and_stops(config_path, kind):
    # a 4 cm block whose top is 5 cm under the tool, on a table no wider than it
    arm, clock, top = _cell(config_path, obj=_block(0.04), below_tool_m=0.05, table_size_m=0.04)
    token = _lower_until_fault(arm, clock, 3.0)
    # not before the bounding spheres reach the block: 5 cm at 10 cm/s after the acceleration ramp
    assert 0.5 <= clock.now() < 3.0
    state = arm.state()
    assert state.mode is ArmMode.FAULT
    (fault,) = state.faults
    assert fault.startswith(f"{kind}: contact: ") and " touched the object (block) at (" in fault
    assert _where(fault)[2] == pytest.approx(top, abs=0.003)  # on the block's top face
    with pytest.raises(RobotFault, match="touched the object"):
        arm.command_twist(SPEED, token)
    for _ in range(50):
        clock.sleep(DT)
    assert np.all(arm.state().qd == 0.0) and arm.state().mode is ArmMode.FAULT


def test_a_body_going_into_the_table_faults_the_arm():
    arm, clock, top = _cell(UR5E, obj=None, below_tool_m=0.03, table_size_m=0.3)
    _lower_until_fault(arm, clock, 3.0)
    (fault,) = arm.state().faults
    assert fault.startswith("protective stop: contact: ") and " touched the table at (" in fault
    assert _where(fault)[2] == pytest.approx(top, abs=0.003)


def test_the_arm_at_rest_or_clear_of_everything_does_not_fault():
    arm, clock, _ = _cell(UR5E, obj=_block(0.04), below_tool_m=0.05, table_size_m=0.04)
    for _ in range(100):
        clock.sleep(DT)
    token = arm.claim_motion()
    arm.command_twist(-SPEED, token)  # up, away
    for _ in range(100):
        clock.sleep(DT)
    assert arm.fault is None and arm.state().faults == ()


def test_the_reviewers_large_box_on_the_tof_cell_ends_with_an_arm_fault(tmp_path):
    """A 0.55 x 0.42 x 0.30 m box at the station: LR-NBV, knowing only the part it has seen, plans into
    it; the scan ends stopped by the arm's protective stop, not completed with the box's walls ranged
    from inside, and keeps its folder and frames."""
    mesh = tmp_path / "box.stl"
    trimesh.creation.box([0.55, 0.42, 0.30]).export(mesh)
    out = tmp_path / "job"
    run = CliRunner().invoke(app, ["scan", "--config", str(UR5E), "--object", str(mesh), "--out", str(out)])
    assert run.exit_code == 1, run.output
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "stopped"
    assert result["termination"].startswith("safety stop: arm fault: protective stop: contact: ")
    assert " touched the object (box) at (" in result["termination"]
    frames = sorted((out / "frames").glob("*.npz"))
    assert len(frames) >= 1 and len(frames) == result["n_captures"]
    assert (out / "cloud.ply").exists() and "touched the object" in (out / "log.txt").read_text()


def test_the_clearances_that_let_steps_go_unchecked_are_lower_bounds():
    """Every body's clearance (what lets the sim skip the check of a step) is at most its true distance to
    the object's mesh, in configurations around the block; the arm at home is clear of it."""
    cfg = load_config(UR5E)
    model = get_robot_model("ur5e")
    clock = SimClock()
    assert isinstance(cfg.arm, SimArmConfig)
    arm = SimArm(cfg.arm, model, clock)
    bodies = CollisionWorld(model, cfg.safety.collision, 0.0).arm_bodies()
    x, y = arm.true_flange_pose()[:2, 3]
    block = _block(0.1)
    scene = SimScene(block, make_T(np.eye(3), np.array([x, y, 0.2])), table_z=0.0)
    contact = SimContact(clock, arm, scene, bodies)
    mesh = fcl.CollisionObject(mesh_bvh(scene.object_vertices_base, scene.object_triangles))
    rng = np.random.default_rng(0)
    for k in range(30):
        q = arm.joints + (0.0 if k == 0 else rng.normal(0.0, 0.15, model.n_joints))
        frames = model.fk_all(q)
        hit, clearance = contact.check(frames)
        if k == 0:
            assert hit is None and np.all(clearance > 0.0)
        if hit is not None:
            continue
        for body, bound in zip(bodies, clearance, strict=True):
            obj = fcl.CollisionObject(body.geometry, fcl_transform(frames[body.frame] @ body.T_frame_body))
            distance = fcl.distance(obj, mesh, fcl.DistanceRequest(), fcl.DistanceResult())
            assert bound <= distance + 1e-9 or distance < 0.0, body.name
