"""Calibration by the cell itself (the ``calibration`` package, ``cell calibrate``): the simulated sensor
really sits at ``sim.true_mount``, the cell file believes ``mount``, and the calibration must find the
truth from views it runs through the safety layer."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from calibration.board_fit import fit_mount_to_board, load_board_views
from calibration.cell_file import updated_text
from calibration.mount import BOARD_ELEVATION_DEG, calibrate_mount, pose_difference
from calibration.predict import check_views_observable
from calibration.table import fit_table
from calibration.targets import box_target
from calibration.tof import ZoneFit, calibrate_zones
from calibration.views import capture_views, mount_views
from cell.cli import calibrate as calibrate_cli
from cell.cli.main import app
from cell.config import load_config
from cell.config.load import parse_config
from cell.config.models import CalibrationConfig, CellConfig, PoseConfig
from drivers.depth.base import SensorModel
from drivers.depth.config import VL53L8CXConfig, ZoneBiasConfig
from drivers.depth.vl53l8cx.emulator import SimToFSource, VL53L8CXEmulator
from drivers.depth.vl53l8cx.serial_driver import VL53L8CXSerial
from drivers.depth.zone_correction import ZoneCorrection, write_zone_correction
from drivers.errors import CalibrationError, ConfigError
from drivers.sim.board import BoardConfig, SimBoardConfig
from drivers.transforms import look_at
from tests.conftest import CONFIG_DIR, FRANKA, UR5E
from tests.rtde_peer import ControllerPeer

TRUE_OFFSET_XYZ_M = (0.006, -0.005, 0.004)
TRUE_OFFSET_RPY_DEG = (2.0, -3.0, 2.5)  # 8.8 mm and 4.4 deg from the believed mount


def _with_true_mount(cfg: CellConfig) -> tuple[CellConfig, PoseConfig]:
    """The cell with its sensor really at ``true`` and no other calibration error (``sim.exact``), so that
    the mount found can be held to the truth."""
    m = cfg.mount
    true = PoseConfig(xyz_m=tuple(np.add(m.xyz_m, TRUE_OFFSET_XYZ_M)),
                      rpy_deg=tuple(np.add(m.rpy_deg, TRUE_OFFSET_RPY_DEG)))
    sim = cfg.sim.model_copy(update={"true_mount": true, "exact": True})
    return cfg.model_copy(update={"sim": sim}), true


def _small_rgbd(cfg: CellConfig) -> CellConfig:
    """The Franka cell's camera at a quarter of its resolution (same field of view), so a test runs fast."""
    s = cfg.sensor.model_copy(update={"width": 160, "height": 120, "fx": 118.75, "fy": 118.75, "cx": 79.5,
                                      "cy": 59.5})
    return cfg.model_copy(update={"sensor": s})


@pytest.mark.parametrize(("cell", "n_poses", "tol_mm", "tol_deg"), [
    ("tof", 40, 3.0, 0.5),
    ("rgbd", 10, 1.0, 0.2),
])
def test_the_known_shape_recovers_a_perturbed_mount(tmp_path: Path, cell: str, n_poses: int, tol_mm: float,
                                                    tol_deg: float) -> None:
    cfg = load_config(UR5E if cell == "tof" else FRANKA)
    cfg, true = _with_true_mount(cfg if cell == "tof" else _small_rgbd(cfg))
    # the box is not where the station is: the fit finds it
    cal = calibrate_mount(cfg, "test", target="horizontal_box", n_poses=n_poses, folder=tmp_path / "views",
                          object_pose=(0.02, -0.01, 8.0))
    start_mm, start_deg = pose_difference(cfg.mount.matrix(), true.matrix())
    err_m, err_deg = pose_difference(cal.fit.T_flange_sensor, true.matrix())
    assert start_mm > 0.008 and start_deg > 4.0
    assert err_m * 1e3 <= tol_mm and err_deg <= tol_deg, (err_m, err_deg)
    # the uncertainty it reports covers the error it made
    assert np.all(cal.fit.std_m > 0.0) and err_m <= 4.0 * float(np.linalg.norm(cal.fit.std_m))
    np.testing.assert_allclose(cal.fit.box_pose[:2], [0.47, -0.01], atol=0.005)
    assert abs(np.degrees(cal.fit.box_pose[2]) - 8.0) < 1.0
    # the raw views and poses are kept, and views that could not be visited were skipped and counted
    assert len(list((tmp_path / "views" / "frames").glob("*.npz"))) == cal.job_result["n_captures"]
    assert cal.fit.n_views + cal.job_result["n_unreachable_views"] + \
        sum(cal.job_result["refused_moves"].values()) == n_poses


def _straight_down(cfg: CellConfig, n: int) -> list[np.ndarray]:
    """Sensor poses looking straight down at the station from n places, all with one orientation."""
    x, y = cfg.station.xy_m
    return [look_at(np.array([x + dx, y + dy, 0.45]), np.array([x + dx, y + dy, 0.0]),
                    up_hint=np.array([1.0, 0.0, 0.0]))
            for dx, dy in zip(np.linspace(-0.06, 0.06, n), np.linspace(0.04, -0.04, n), strict=True)]


def test_views_of_one_orientation_are_refused_naming_the_axis_before_anything_moves(tmp_path: Path) -> None:
    cfg = load_config(UR5E)
    box = box_target("horizontal_box")
    model = SensorModel(kind="tof", width=8, height=8, fov_x_deg=45.0, fov_y_deg=45.0, range_min_m=0.02,
                        range_max_m=4.0)
    mount = cfg.mount.matrix()
    views = _straight_down(cfg, 8)
    flange = [T @ np.linalg.inv(mount) for T in views]
    box0 = np.array([*cfg.station.xy_m, 0.0])
    # translations alone: the mount's position trades against where the box and the table are
    with pytest.raises(CalibrationError, match=r"cannot observe the mount's (x|y|z)\b"):
        check_views_observable(model, flange, mount, box, box0, 0.0)
    # the planned views of the calibration observe every axis
    spread = [T @ np.linalg.inv(mount) for T in mount_views(cfg, 24, 0.1, cfg.scan.standoff_m)]
    check_views_observable(model, spread, mount, box, box0, 0.0)

    def precheck(m: SensorModel, poses: list[np.ndarray]) -> None:
        check_views_observable(m, [T @ np.linalg.inv(mount) for T in poses], mount, box, box0, 0.0)

    with pytest.raises(CalibrationError, match="cannot observe"):
        capture_views(cfg, "test", views, target_object="horizontal_box", folder=tmp_path / "job",
                      precheck=precheck)
    result = json.loads((tmp_path / "job" / "result.json").read_text())
    assert result["status"] == "failed" and "cannot observe" in result["termination"]
    assert result["path_length_m"] == 0.0 and result["n_captures"] == 0


def _tof_cell_with_true_mount(tmp_path: Path) -> Path:
    text = UR5E.read_text().replace(
        "  true_mount: null", "  true_mount: {xyz_m: [0.006, 0.035, 0.034], rpy_deg: [2.0, -3.0, 2.5]}  #")
    text = text.replace("  exact: false", "  exact: true")  # no calibration error but the mount's
    path = tmp_path / "cell.yaml"
    path.write_text(text)
    return path


def test_cli_mount_writes_the_result_and_the_cell_file_keeping_its_comments(tmp_path: Path) -> None:
    cell = _tof_cell_with_true_mount(tmp_path)
    before = cell.read_text()
    out = tmp_path / "mount.json"
    run = CliRunner().invoke(app, ["calibrate", "mount", "--config", str(cell), "--out", str(out), "--poses",
                                   "20", "--data-dir", str(tmp_path / "data"), "--write"])
    assert run.exit_code == 0, run.output
    result = json.loads(out.read_text())
    assert set(result) >= {"mount", "residual_mm", "n_views", "std_mm", "std_deg"}
    assert "--- " in run.output and "wrote the mount into" in run.output  # the change was shown
    after = cell.read_text()
    # every line but the two of the mount is as it was, comments and all
    changed = [(a, b) for a, b in zip(before.splitlines(), after.splitlines(), strict=True) if a != b]
    assert [a.split(":")[0].strip() for a, _ in changed] == ["xyz_m", "rpy_deg"]
    cfg = load_config(cell)
    assert list(cfg.mount.xyz_m) == result["mount"]["xyz_m"]
    err_m, err_deg = pose_difference(cfg.mount.matrix(), cfg.true_mount_matrix())
    assert err_m <= 0.005 and err_deg <= 0.5  # 20 views only (the accuracy of 40: the test above)
    kept = list((tmp_path / "data" / "calibrations").iterdir())
    assert len(kept) == 1 and (kept[0] / "calibration.json").is_file() and (kept[0] / "frames").is_dir()

    # a second calibration of the same cell agrees with the first within their uncertainties
    (tmp_path / "again.json").write_text(json.dumps({**result, "mount": {
        "xyz_m": list(np.add(result["mount"]["xyz_m"], [0.0005, 0.0, 0.0])),
        "rpy_deg": result["mount"]["rpy_deg"]}}))
    run = CliRunner().invoke(app, ["calibrate", "compare", str(out), str(tmp_path / "again.json")])
    assert run.exit_code == 0, run.output
    assert "x 0.500" in run.output and "consistent within their uncertainties" in run.output


@pytest.mark.parametrize(("content", "problem"), [
    (None, "cannot read {b}: no such file"),  # was "... is not a mount calibration result: [Errno 2] ..."
    ({"planner": "raster", "status": "completed"},  # a job's result.json; was "...: 'mount'" (a KeyError)
     "{b} has no 'mount' section: it is not a mount calibration result (a job's result.json?); cell "
     "calibrate mount --out writes one"),
    ({"mount": {"xyz_m": [0.0, 0.04]}},
     "{b} is not a mount calibration result: mount.xyz_m.2: Field required"),
])
def test_compare_says_what_is_wrong_with_a_file_that_is_no_mount_result(tmp_path: Path, content: object,
                                                                          problem: str) -> None:
    a, b = tmp_path / "mount.json", tmp_path / "other.json"
    a.write_text(json.dumps({"mount": {"xyz_m": [0.0, 0.04, 0.03], "rpy_deg": [0.0, 0.0, 0.0]}}))
    if content is not None:
        b.write_text(json.dumps(content))
    run = CliRunner().invoke(app, ["calibrate", "compare", str(a), str(b)])
    assert run.exit_code == 1 and run.stderr == f"error: {problem.format(b=b)}\n"


def test_write_replaces_measure_marks_and_touches_nothing_else() -> None:
    hardware = CONFIG_DIR / "ur5e-vl53l8cx.yaml"
    text = hardware.read_text()
    new = updated_text(text, {("mount", "xyz_m"): [0.001, 0.04123, 0.03],
                              ("mount", "rpy_deg"): [0.5, -0.25, 1.0],
                              ("sensor", "zone_correction"): "zones.json"}, "cell.yaml", "calibrated")
    old_lines, new_lines = text.splitlines(), new.splitlines()
    added = [line for line in new_lines if line not in old_lines]
    assert added == ['  zone_correction: "zones.json"  # calibrated',
                     "  xyz_m: [0.001, 0.04123, 0.03] # calibrated",
                     "  rpy_deg: [0.5, -0.25, 1.0]   # calibrated"]
    assert len(new_lines) == len(old_lines) + 1
    cfg = parse_config(yaml.safe_load(new), file="cell.yaml")
    assert cfg.mount.rpy_deg == (0.5, -0.25, 1.0) and cfg.sensor.zone_correction == "zones.json"


def test_the_board_method_needs_the_cells_board(tmp_path: Path) -> None:
    run = CliRunner().invoke(app, ["calibrate", "mount", "--config", str(UR5E), "--out",
                                   str(tmp_path / "m.json"), "--target", "charuco"])
    assert run.exit_code == 1 and "no calibration.board" in run.output


def test_the_printable_board_is_the_cells_board_at_its_size(tmp_path: Path) -> None:
    """``cell calibrate board`` writes the cell file's ``calibration.board`` as a PNG whose resolution
    prints a square ``square_m`` wide, and a detector finds every inner corner of it."""
    from PIL import Image

    cell_file = CONFIG_DIR / "franka-realsense.yaml"
    spec = load_config(cell_file).calibration.board
    assert spec is not None
    out = tmp_path / "board.png"
    run = CliRunner().invoke(app, ["calibrate", "board", "--config", str(cell_file), "--out", str(out),
                                   "--dpi", "200", "--margin", "0.005"])
    assert run.exit_code == 0, run.output
    assert f"wrote {out}: 7 x 5 squares of 30 mm, markers of 22 mm (DICT_5X5_100)" in run.output
    with Image.open(out) as png:
        image = np.asarray(png.convert("L"))
        dpi = png.info["dpi"][0]
    px_per_m = dpi / 0.0254
    margin_px = round(0.005 * px_per_m)
    printed_m = np.array(image.shape) / px_per_m  # board and margins, to the pixel
    assert np.allclose(printed_m, (5 * 0.03 + 0.01, 7 * 0.03 + 0.01), atol=1.5 / px_per_m)
    assert abs(dpi - 200.0) < 2.0 and (image[:margin_px] == 255).all()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(spec.opencv()).detectBoard(image)
    assert ids is not None and sorted(ids.ravel()) == list(range(6 * 4))
    # the corners lie a square apart in print: square_m at the PNG's resolution
    by_id = dict(zip(ids.ravel(), corners.reshape(-1, 2), strict=True))
    assert np.linalg.norm(by_id[1] - by_id[0]) / px_per_m == pytest.approx(0.03, abs=1e-4)


def test_a_board_needs_the_cell_files_board(tmp_path: Path) -> None:
    run = CliRunner().invoke(app, ["calibrate", "board", "--config", str(UR5E), "--out",
                                   str(tmp_path / "b.png")])
    assert run.exit_code == 1 and "no calibration.board" in run.output and not (tmp_path / "b.png").exists()


def test_the_board_recovers_a_perturbed_mount_and_views_without_it_are_skipped(tmp_path: Path) -> None:
    cfg, true = _with_true_mount(load_config(FRANKA))
    cfg = cfg.model_copy(update={"calibration": CalibrationConfig(board=BoardConfig()),
                                 "sim": cfg.sim.model_copy(update={"board": SimBoardConfig(pose=(0.01, 0.005,
                                                                                                 5.0))})})
    views = mount_views(cfg, 10, 0.0, 0.3, elevation_deg=BOARD_ELEVATION_DEG)
    x, y = cfg.station.xy_m
    away = [look_at(np.array([x - 0.1, y + dy, 0.35]), np.array([x - 0.1, y + dy + 0.3, 0.0]))
            for dy in (-0.1, 0.1)]  # the board is out of sight
    capture_views(cfg, "test", views[:5] + away + views[5:], target_object="none", folder=tmp_path / "views")
    board_views, missing = load_board_views(tmp_path / "views", BoardConfig())
    assert missing == 2
    fit = fit_mount_to_board(board_views, missing)
    err_m, err_deg = pose_difference(fit.T_flange_sensor, true.matrix())
    assert err_m <= 0.0005 and err_deg <= 0.2, (err_m, err_deg)
    assert fit.method in ("tsai", "park", "daniilidis") and fit.residual_px < 0.5
    assert fit.record()["n_views_without_board"] == 2


def test_the_zone_calibration_finds_each_zones_bias_and_halves_the_range_error(tmp_path: Path) -> None:
    cfg = load_config(UR5E)
    bias = ZoneBiasConfig(offset_std_m=0.01, seed=3)
    sensor = cfg.sensor.model_copy(update={"zone_bias": bias})
    cfg, _ = _with_true_mount(cfg.model_copy(update={"sensor": sensor}))
    fit = calibrate_zones(cfg, "test", folder=tmp_path / "views", frames_per_height=6)
    truth = bias.offset_std_m * np.random.default_rng(bias.seed).standard_normal(64)
    # the biases up to their common part (the mount's business), despite the wrong mount
    assert np.abs(fit.correction.offset_m - (truth - truth.mean())).mean() < 0.002
    assert fit.error_after_m <= 0.5 * fit.error_before_m
    np.testing.assert_allclose(fit.correction.noise_m.mean(), 0.005, atol=0.0015)  # sigma0 + k r^2

    # the correction file, applied by the simulated sensor, leaves no bias to find
    path = tmp_path / "zones.json"
    write_zone_correction(fit.correction, path)
    sensor = cfg.sensor.model_copy(update={"zone_correction": str(path)})
    corrected = cfg.model_copy(update={"sensor": sensor})
    again = calibrate_zones(corrected, "test", folder=tmp_path / "again", frames_per_height=6)
    assert again.error_before_m < 0.6 * fit.error_before_m
    np.testing.assert_allclose(again.correction.offset_m, fit.correction.offset_m, atol=0.004)


def test_the_serial_driver_applies_the_zone_correction(tmp_path: Path) -> None:
    offsets = np.linspace(-0.02, 0.02, 16)
    path = tmp_path / "zones.json"
    write_zone_correction(ZoneCorrection(resolution=4, offset_m=offsets, noise_m=np.zeros(16)), path)
    emulator = VL53L8CXEmulator.on_tcp(SimToFSource.fixed("cube", seed=1), seed=2)
    config = VL53L8CXConfig(type="vl53l8cx", port=emulator.url, resolution=4, frequency_hz=60, timeout_s=2.0,
                            zone_correction=str(path))
    sensor = VL53L8CXSerial(config)
    with emulator, sensor:
        frames = [(sensor.capture(), sensor.last_raw) for _ in range(3)]
    for frame, raw in frames:
        assert raw is not None
        has = raw.nb_target_detected > 0
        np.testing.assert_allclose(frame.zones.distance_m[has], raw.distance_mm[has] / 1000.0 - offsets[has],
                                   atol=1e-6)  # the file holds 6 decimals
        valid = has & np.isin(raw.target_status, [5, 9]) & (raw.distance_mm > 0)
        np.testing.assert_allclose(np.linalg.norm(frame.points, axis=1),
                                   raw.distance_mm[valid] / 1000.0 - offsets[valid], atol=1e-6)
    # a table for another resolution is refused when the driver is made, naming the file
    with pytest.raises(ConfigError, match=r"zones\.json.*4x4 zones, the sensor runs 8x8"):
        VL53L8CXSerial(config.model_copy(update={"resolution": 8, "frequency_hz": 15}))


def test_a_calibration_on_the_dry_run_path_moves_the_rtde_peer_through_the_guard(tmp_path: Path) -> None:
    dry_run = CONFIG_DIR / "dryrun-ur5e-peer.yaml"
    cfg = load_config(dry_run)
    assert cfg.arm.home_joints_rad is not None
    peer = ControllerPeer(q=cfg.arm.home_joints_rad)
    try:
        cfg = cfg.model_copy(update={"arm": cfg.arm.model_copy(update={"host": peer.host})})
        cal = calibrate_mount(cfg, str(dry_run), target="horizontal_box", n_poses=6,
                              folder=tmp_path / "views")
        servoj = peer.records("servoJ")
        peer_state = peer.state()
    finally:
        peer.stop()
    result = cal.job_result
    assert result["status"] == "completed" and result["safety"]["stops"] == [], result["termination"]
    assert servoj and peer_state["safety_mode"] == "NORMAL" and result["path_length_m"] > 0.1
    assert cal.fit.n_views >= 4 and len(list((tmp_path / "views" / "frames").glob("*.npz"))) >= 4 * 5
    # a handful of views: the mount is found within the uncertainty the fit reports
    err_m, err_deg = pose_difference(cal.fit.T_flange_sensor, cfg.true_mount_matrix())
    assert err_m <= 4.0 * float(np.linalg.norm(cal.fit.std_m)) and err_deg <= 1.0


def test_the_table_fit_starts_from_the_table_not_from_a_part_standing_on_it() -> None:
    """A 10 cm part over a tenth of the points: a least-squares start on every point lies between the part
    and the table, and trimming about it kept neither; from the lowest band of heights that holds a share
    of the points the fit finds the table, 0.5 mm up, and the part above it."""
    rng = np.random.default_rng(0)
    table = np.column_stack([rng.uniform([0.25, -0.2], [0.65, 0.2], (20000, 2)),
                             0.0005 + rng.normal(0.0, 0.0005, 20000)])
    part = np.column_stack([rng.uniform([0.4, -0.05], [0.5, 0.05], (2000, 2)),
                            0.1 + rng.normal(0.0, 0.0005, 2000)])
    fit = fit_table(np.vstack([table, part]))
    np.testing.assert_allclose(fit.coefficients, [0.0, 0.0, 0.0005], atol=1e-4)
    assert fit.n_points > 19000
    assert fit.part_xy_m is not None and np.allclose(fit.part_xy_m, [0.45, 0.0], atol=0.005)


def test_the_table_fit_starts_from_the_table_under_a_part_that_fills_most_of_the_views() -> None:
    """The 0.30 x 0.20 m box fills most of the views, and a start about the median height found its top:
    the table is the lowest extended plane, the part stands on it."""
    rng = np.random.default_rng(1)
    table = np.column_stack([rng.uniform([0.25, -0.2], [0.65, 0.2], (3000, 2)),
                             0.0005 + rng.normal(0.0, 0.005, 3000)])
    part = np.column_stack([rng.uniform([0.3, -0.1], [0.6, 0.1], (17000, 2)),
                            0.1 + rng.normal(0.0, 0.005, 17000)])
    below = np.column_stack([rng.uniform([0.25, -0.2], [0.65, 0.2], (20, 2)), rng.uniform(-0.3, -0.05, 20)])
    fit = fit_table(np.vstack([table, part, below]))
    np.testing.assert_allclose(fit.coefficients, [0.0, 0.0, 0.0005], atol=1e-3)
    assert fit.part_xy_m is not None and np.allclose(fit.part_xy_m, [0.45, 0.0], atol=0.005)


@pytest.mark.parametrize("target", ["horizontal_box", "cube"])
def test_cli_table_on_the_tof_cell_finds_the_table_under_each_part(tmp_path: Path, target: str) -> None:
    out = tmp_path / "table.json"
    run = CliRunner().invoke(app, ["calibrate", "table", "--config", str(UR5E), "--out", str(out),
                                   "--object", target, "--data-dir", str(tmp_path / "data")])
    assert run.exit_code == 0, run.output
    report = json.loads(out.read_text())
    # the sim's calibration errors (a 2 mm depth bias, the mount's) and 5 mm of range noise: a few mm
    assert abs(report["table_z_difference_mm"]) < 5.0 and report["tilt_deg"] < 1.0
    assert report["part_xy_m"] is not None and np.hypot(*report["station_difference_mm"]) < 10.0
    assert f"wrote {out}; views kept in " in run.output


def test_cli_table_finds_the_table_and_the_part_on_the_station(tmp_path: Path) -> None:
    cell = tmp_path / "cell.yaml"
    data = yaml.safe_load(FRANKA.read_text())
    data["sensor"].update(width=160, height=120, fx=118.75, fy=118.75, cx=79.5, cy=59.5)  # fast
    data["sim"]["exact"] = True  # the table where the cell file says: a depth bias would move it
    cell.write_text(yaml.safe_dump(data))
    out = tmp_path / "table.json"
    run = CliRunner().invoke(app, ["calibrate", "table", "--config", str(cell), "--out", str(out),
                                   "--object", "cube", "--data-dir", str(tmp_path / "data")])
    assert run.exit_code == 0, run.output
    report = json.loads(out.read_text())
    assert abs(report["table_z_difference_mm"]) < 0.5 and report["tilt_deg"] < 0.05
    # the centre of what the views saw of the cube: its top and the sides they faced
    assert report["part_xy_m"] is not None and np.hypot(*report["station_difference_mm"]) < 10.0
    assert "part on the station" in run.output


def test_a_zone_correction_that_does_not_reduce_the_held_back_error_is_not_written(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """2.13 mm before and 2.21 mm after was written into the cell file without a word."""
    cell = tmp_path / "cell.yaml"
    cell.write_text(UR5E.read_text())
    correction = ZoneCorrection(resolution=8, offset_m=np.full(64, 0.001), noise_m=np.full(64, 0.002))
    fit = ZoneFit(correction=correction, height0_m=0.15, toward_table=np.array([0.0, 0.0, 1.0]),
                  error_before_m=0.00213, error_after_m=0.00221, n_frames=40)
    monkeypatch.setattr(calibrate_cli, "calibrate_zones", lambda *args, **kwargs: fit)
    out = tmp_path / "zones.json"
    run = CliRunner().invoke(app, ["calibrate", "tof", "--config", str(cell), "--out", str(out), "--write",
                                   "--data-dir", str(tmp_path / "data")])
    assert run.exit_code == 1
    assert "2.13 mm before, 2.21 mm after" in run.output
    assert "the correction does not reduce the held-back range error: not written" in run.output
    assert not out.exists() and cell.read_text() == UR5E.read_text()
    assert len(list((tmp_path / "data" / "calibrations").glob("*/zone_correction.json"))) == 1
