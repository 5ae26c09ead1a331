"""What the sensor has seen standing on the table is an obstacle outside the object's ROI
(``cell.perception.seen_obstacles``, ``CollisionWorld.set_seen``), from a look before the first move
(``JobSession.survey``) on: a part put off the station, outside the crop box that perception keeps, is not
run into."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import fcl
import numpy as np
import pytest

from cell.config import load_config
from cell.perception.pipeline import PerceptionPipeline
from cell.perception.seen_obstacles import SeenCells, SeenObstacles, sample_pitch_rad
from cell.safety.collision import ROI_ARM_CLEARANCE_M, CollisionWorld
from cell.safety.guard import MotionGuard
from drivers.depth.base import DepthFrame, ToFZones
from drivers.depth.projection import back_project
from drivers.fcl_bodies import fcl_transform
from drivers.robots import get_robot_model

from .conftest import CONFIG_DIR
from .safety_rig import CELLS

TOF = CONFIG_DIR / "sim-ur5e-tof.yaml"

G = 0.01  # the grid's edge [m] in these tests


def _looking_down(height_m: float) -> np.ndarray:
    """A sensor pose (base frame) at ``height_m`` over the origin, its z axis down."""
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[2, 3] = height_m
    return T


def test_only_returns_within_reach_and_above_the_table_band_and_noise_mark_cells() -> None:
    T = _looking_down(0.5)
    # 4 mm, 8 mm, 50 mm and 30 mm above the table, the last beyond the arm's reach (0.6 m here)
    points = np.array([[0.0, 0.0, 0.496], [0.1, 0.0, 0.492], [0.2, 0.0, 0.45], [0.7, 0.0, 0.47]])
    seen = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006, reach_m=0.6)
    seen.add(points, T, pitch_rad=0.0)
    assert np.allclose(seen.outside(None).centers(), [[0.105, 0.005, 0.005], [0.205, 0.005, 0.045]])
    # a median range sigma of 5 mm lifts the band by 15 mm: only the return 50 mm up is left, however
    # large its own sigma (a zone on a part's edge), and a zone without one changes nothing
    ranged = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006, reach_m=0.6)
    ranged.add(points, T, pitch_rad=0.0, sigma_m=np.array([0.005, 0.005, 0.05, np.nan]))
    assert np.allclose(ranged.outside(None).centers(), [[0.205, 0.005, 0.045]])


def test_a_sparse_sensor_s_return_stands_for_the_gap_to_its_neighbours() -> None:
    """Returns 3.9 cm apart (an 8x8 ToF zone at 0.4 m) grow by two cells on each side, so the cells of two
    neighbouring returns meet; returns closer than a cell apart do not grow."""
    pitch = np.radians(45.0 / 8.0)
    sparse = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006)
    sparse.add(np.array([[0.0, 0.0, 0.4]]), _looking_down(0.5), pitch_rad=pitch)
    cells = sparse.outside(None)
    assert len(cells) == 5 ** 3
    assert np.ptp(cells.centers(), axis=0) == pytest.approx([0.04, 0.04, 0.04])
    dense = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006)
    dense.add(np.array([[0.0, 0.0, 0.4]]), _looking_down(0.5), pitch_rad=0.001)
    assert len(dense.outside(None)) == 1


def test_what_lies_within_a_cell_of_the_roi_is_the_object_s_and_a_part_beside_it_is_not() -> None:
    seen = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006)
    # returns 5 mm and 2.5 cm beside a ROI box, each 3.2-3.3 cm from its neighbours (a reach of 2 cells)
    seen.add(np.array([[0.005, 0.0, 0.4], [0.025, 0.0, 0.4]]), _looking_down(0.5), pitch_rad=0.08)
    roi = (np.array([-0.05, -0.05, 0.0]), np.array([0.0, 0.05, 0.1]))
    kept = seen.outside(roi).centers()
    assert len(kept) == 5 ** 3 and kept[:, 0].min() == pytest.approx(0.005)
    assert len(seen.outside(None)) == 7 * 5 * 5


def test_the_surface_of_the_cells_is_their_union_s_boundary() -> None:
    seen = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006)
    seen.add(np.array([[0.005, 0.005, 0.455], [0.015, 0.005, 0.455]]), _looking_down(0.5), pitch_rad=0.0)
    vertices, triangles = seen.outside(None).surface
    assert triangles.shape == (2 * 10, 3)  # two cells side by side: ten open faces
    assert vertices.min(axis=0) == pytest.approx([0.0, -0.01, 0.04])
    assert vertices.max(axis=0) == pytest.approx([0.02, 0.0, 0.05])


def test_a_block_that_holds_the_cells_it_held_keeps_its_body() -> None:
    """Cells in two blocks (16 cells a side), then a cell more in one of them: the other block is the one
    built before, body and all; the grown one is built again, and its body holds the new cell."""
    seen = SeenObstacles(G, table_z_m=0.0, table_band_m=0.006)
    seen.add(np.array([[0.005, 0.005, 0.455], [0.305, 0.005, 0.455]]), _looking_down(0.5), pitch_rad=0.0)
    first = [chunk for chunk, _ in seen.outside(None).chunks]
    again = [chunk for chunk, _ in seen.outside(None).chunks]
    assert len(first) == 2 and all(a is b for a, b in zip(first, again, strict=True))
    seen.add(np.array([[0.015, 0.005, 0.455]]), _looking_down(0.5), pitch_rad=0.0)
    grown, kept = (chunk for chunk, _ in seen.outside(None).chunks)
    assert kept is first[1] and grown is not first[0] and len(grown) == 2
    assert grown.body[2] > first[0].body[2]


def test_the_pitch_of_a_frame_s_returns() -> None:
    angles = np.radians([-2.0, 3.0])
    directions = np.column_stack([np.sin(angles), np.zeros(2), np.cos(angles)])
    zones = ToFZones(distance_m=np.ones(2), sigma_m=np.zeros(2), status=np.full(2, 5, dtype=np.uint8),
                     nb_targets=np.ones(2, dtype=np.uint8), reflectance_pct=np.ones(2), directions=directions)
    assert sample_pitch_rad(DepthFrame(0, 0.0, directions, zones=zones)) == pytest.approx(np.radians(5.0))
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    assert sample_pitch_rad(DepthFrame(0, 0.0, np.zeros((0, 3)), intrinsics=K)) == pytest.approx(0.002)
    assert sample_pitch_rad(DepthFrame(0, 0.0, np.zeros((0, 3)))) == 0.0


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_seen_cells_on_the_arm_s_way_are_an_obstacle_but_where_the_arm_stands(model_name: str) -> None:
    """A column of cells below the flange: the way down to it is refused, also after the way ahead was
    cleared many times without it; the cells the arm stands in are left out (counted), and without cells
    the way is clear again."""
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    world = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m)
    q_home = np.asarray(cfg.arm.home_joints_rad)
    T = model.fk(q_home)
    T[2, 3] -= 0.2
    q_down = model.ik_pose(T, q_home)
    for _ in range(5):
        assert world.check_motion(q_home, q_down) is None
    seen = SeenObstacles(G, table_z_m=cfg.station.table_z_m, table_band_m=0.006)
    flange = model.fk(q_home)[:3, 3]
    column = flange - np.column_stack([np.zeros((40, 2)), np.linspace(0.0, 0.3, 40)])
    seen.add(column, np.eye(4), pitch_rad=0.0)
    cells = seen.outside(None)
    assert world.set_seen(cells, q_free=q_home) > 0
    hit = world.check_motion(q_home, q_down)
    assert hit is not None and hit[1].body_b == "seen obstacle"
    path_hit = world.check_path(np.array([q_home, q_down]), 0.02)
    assert path_hit is not None and path_hit[1].body_b == "seen obstacle"
    assert world.check(q_home) is None  # the cells at the arm were left out
    # the same cells again keep the body, and the distances the way ahead keeps with it: the next check
    # measures only what every check measures
    assert world.check_motion(q_home, q_home) is None
    before = world.n_distances
    world.check_motion(q_home, q_home)
    every_check = world.n_distances - before
    world.set_seen(seen.outside(None), q_free=q_home)
    before = world.n_distances
    assert world.check_motion(q_home, q_home) is None and world.n_distances - before == every_check
    world.set_seen(None)
    assert world.check_motion(q_home, q_down) is None


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_the_cells_left_out_are_those_the_arm_s_bodies_come_within_its_clearance_of(model_name: str) -> None:
    """Cells all about the arm at home: exactly those whose cube one of its bodies (links and tool, FCL's
    distance) comes within ``ROI_ARM_CLEARANCE_M`` of are left out, not every one a ball about the cube
    reaches."""
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    world = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m)
    q = np.asarray(cfg.arm.home_joints_rad)
    frames = model.fk_all(q)
    bodies = [(b.geometry, frames[b.frame] @ b.T_frame_body) for b in world.arm_bodies()]
    anchors = np.array([T[:3, 3] for _, T in bodies])
    rng = np.random.default_rng(3)
    points = (anchors[rng.integers(0, len(anchors), 400)] + rng.uniform(-0.12, 0.12, (400, 3)))
    seen = SeenObstacles(G, table_z_m=-1.0, table_band_m=0.0)
    seen.add(points, np.eye(4), pitch_rad=0.0)
    cells = seen.outside(None)
    cube = fcl.Box(G, G, G)

    def touches(center: np.ndarray) -> bool:
        cell = fcl.CollisionObject(cube, fcl.Transform(center))
        return any(fcl.distance(fcl.CollisionObject(geometry, fcl_transform(T)), cell, fcl.DistanceRequest(),
                                fcl.DistanceResult()) <= ROI_ARM_CLEARANCE_M for geometry, T in bodies)

    expected = sum(touches(c) for c in cells.centers())
    assert 0 < expected < len(cells)
    assert world.set_seen(cells, q_free=q) == expected


@pytest.mark.parametrize("model_name", ["ur5e", "panda"])
def test_no_body_of_the_arm_comes_further_from_its_base_than_its_reach(model_name: str) -> None:
    """``CollisionWorld.reach_m``, beyond which a scan keeps no return: every capsule's ends at 2000 random
    configurations lie within it, less the capsule's radius; it is no more than a link's length over."""
    cfg = load_config(CELLS[model_name])
    model = get_robot_model(model_name)
    world = CollisionWorld(model, cfg.safety.collision, cfg.station.table_z_m)
    rng = np.random.default_rng(4)
    farthest = 0.0
    for q in rng.uniform(model.q_min, model.q_max, (2000, model.n_joints)):
        for c in model.capsules(q):
            farthest = max(farthest, max(float(np.linalg.norm(c.a)), float(np.linalg.norm(c.b))) + c.radius)
    assert farthest <= world.reach_m <= farthest + 0.4


def test_a_job_keeps_what_it_sees_within_its_arm_s_reach(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from cell.jobs import runner

    built: list[PerceptionPipeline] = []

    class Kept(PerceptionPipeline):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            built.append(self)

    monkeypatch.setattr(runner, "PerceptionPipeline", Kept)
    cfg = load_config(CELLS["panda"])
    runner.run_scan(runner.ScanRequest(config=cfg, config_path=str(CELLS["panda"]), object="cube",
                                       planner="raster", out=tmp_path / "job", max_time_s=0.5))
    world = CollisionWorld.for_cell(cfg)
    assert [p.seen.reach_m for p in built] == [world.reach_m]


def test_a_survey_adds_to_the_seen_cells_only_and_a_frame_s_update_keeps_those_outside_its_crop_box() -> None:
    cfg = load_config(CELLS["panda"])
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(0))
    T = _looking_down(0.35)  # the table 35 cm ahead, within the crop box (5-40 cm, +-15 cm across)
    far_off = np.array([[0.3, 0.0, 0.3]])  # 5 cm up, 30 cm off the sensor's axis: beyond the crop box
    cells = pipeline.survey(DepthFrame(0, 0.0, far_off), T)
    assert len(cells) == 1 and pipeline.cloud.points.shape[0] == 0 and pipeline.map.n_known == 0
    table = np.column_stack([np.mgrid[-0.05:0.05:0.0025, -0.05:0.05:0.0025].reshape(2, -1).T,
                             np.full(1600, 0.35)])
    update = pipeline.process(DepthFrame(1, 1.0, np.vstack([table, [[-0.3, 0.1, 0.3]]])), T)
    assert len(update.seen) == 2 and update.roi is None
    assert pipeline.cloud.points.shape[0] > 0 and np.all(np.abs(pipeline.cloud.points[:, 0]) < 0.06)


def test_a_camera_s_flying_pixels_at_an_edge_mark_no_cells_and_a_thin_rod_s_top_does() -> None:
    """Straight down from 50 cm onto the table: a box's top 10.5 cm up fills the image's left half, and
    the three pixels of each row beyond its edge lie between it and the table, 7.75, 5.25 and 2.75 cm up
    (flying pixels); a rod 6 mm across (7 pixels) stands 8.5 cm up on the right, and a wire 2 pixels
    across (1.7 mm) 8 cm up above it. The box's top, the rod's and the wire are seen, and nothing between
    the box's edge and the table."""
    cfg = load_config(CELLS["panda"])
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(0))
    K = np.array([[500.0, 0.0, 99.5], [0.0, 500.0, 99.5], [0.0, 0.0, 1.0]])
    depth = np.full((200, 200), 0.5, dtype=np.float32)
    depth[:, :100] = 0.395
    depth[:, 100:103] = [0.4225, 0.4475, 0.4725]
    depth[100:107, 150:157] = 0.415
    depth[30:40, 180:182] = 0.42
    frame = DepthFrame(0, 0.0, back_project(depth, K), depth=depth, intrinsics=K)
    centers = pipeline.survey(frame, _looking_down(0.5)).centers()
    box = centers[:, 0] < 0.0
    assert np.count_nonzero(box) == 8 * 16 and np.allclose(centers[box, 2], 0.105)
    assert np.allclose(centers[~box], [[0.045, -0.005, 0.085], [0.065, 0.055, 0.085]])


def test_a_tof_frame_s_sigmas_lift_the_band_by_their_median() -> None:
    """An 8x8 frame straight down from 40 cm onto the table (ToF cell: band 12 mm), zone sigmas 5 mm: a
    zone 2 cm up stays below the band's 27 mm, one 4 cm up with a 3 cm sigma of its own (an edge) counts."""
    cfg = load_config(TOF)
    pipeline = PerceptionPipeline(cfg.perception, table_z_m=0.0, range_max_m=cfg.sensor.range_max_m,
                                  rng=np.random.default_rng(0))
    angles = np.radians(np.arange(-3.5, 4.0) * 45.0 / 8.0)
    ax, ay = np.meshgrid(angles, angles)
    directions = np.column_stack([np.tan(ax).ravel(), np.tan(ay).ravel(), np.ones(64)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distance = 0.4 / directions[:, 2]
    sigma = np.full(64, 0.005)
    distance[27], distance[36], sigma[36] = distance[27] * 0.95, distance[36] * 0.9, 0.03
    zones = ToFZones(distance_m=distance, sigma_m=sigma, status=np.full(64, 5, dtype=np.uint8),
                     nb_targets=np.ones(64, dtype=np.uint8), reflectance_pct=np.full(64, 50.0),
                     directions=directions)
    frame = DepthFrame(0, 0.0, distance[:, None] * directions, zones=zones)
    cells = pipeline.survey(frame, _looking_down(0.4))
    # the one zone 4 cm up, grown by its reach (3.5 cm to its neighbours: 2 cells)
    assert len(cells) == 5 ** 3
    top = 0.4 - distance[36] * directions[36, 2]
    assert np.mean(cells.centers()[:, 2]) == pytest.approx(np.floor(top / G) * G + G / 2)


def test_a_part_off_the_station_where_the_first_view_goes_is_not_run_into(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch
                                                                         ) -> None:
    """The bunny put 19 cm off the station, where VS-Local's start view takes the camera: no frame of the
    scan sees it in its crop box before the camera would reach it (perception finds no object), but the
    survey from home saw it, and the guard keeps the arm off it. Without the seen obstacles the camera
    touches it at 7.8 s (the sim arm's reflex). The guard takes them in from the survey and from every
    capture's update."""
    from typer.testing import CliRunner

    from cell.cli.main import app

    taken_in = []
    set_seen = MotionGuard.set_seen

    def spy(guard: MotionGuard, cells: SeenCells | None, q_free: np.ndarray | None = None) -> None:
        taken_in.append(len(cells) if cells is not None else None)
        set_seen(guard, cells, q_free)

    monkeypatch.setattr(MotionGuard, "set_seen", spy)
    out = tmp_path / "job"
    res = CliRunner().invoke(app, ["scan", "--planner", "vs-local", "--object", "bunny", "--object-pose",
                                   "0,-0.19,0", "--max-time", "12", "--out", str(out)])
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "completed", res.output
    assert "touched" not in res.output
    assert "survey from home" in (out / "log.txt").read_text()
    assert len(taken_in) == result["n_captures"] + 1 and taken_in[0] > 0
