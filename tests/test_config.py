"""Cell files: every shipped file validates; bad files fail with the file, the field and what is allowed."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.main import app
from cell.config import load_config
from cell.config.load import load_config_data, parse_config
from drivers.depth.zone_correction import ZoneCorrection, write_zone_correction
from drivers.errors import ConfigError

from .conftest import CONFIG_DIR

SHIPPED = sorted(CONFIG_DIR.glob("*.yaml"))


def test_all_four_cells_are_shipped():
    names = {p.name for p in SHIPPED}
    assert {"sim-franka-rgbd.yaml", "sim-ur5e-tof.yaml", "franka-realsense.yaml",
            "ur5e-vl53l8cx.yaml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_cells_validate(path):
    cfg = load_config(path)
    assert cfg.arm.model in ("panda", "ur5e")


def test_sim_cells_match_the_papers():
    franka = load_config(CONFIG_DIR / "sim-franka-rgbd.yaml")
    assert (franka.arm.model, franka.sensor.type) == ("panda", "sim-rgbd")
    assert (franka.sensor.width, franka.sensor.height) == (640, 480)
    assert franka.scan.standoff_m == 0.25
    box = franka.perception.crop_box
    assert (box.x_m, box.y_m, box.z_m) == ((-0.15, 0.15), (-0.15, 0.15), (0.05, 0.40))
    ur = load_config(CONFIG_DIR / "sim-ur5e-tof.yaml")
    sensor = ur.sensor
    assert (ur.arm.model, sensor.type, sensor.resolution, sensor.fov_deg) == ("ur5e", "sim-tof", 8, 45.0)


@pytest.mark.parametrize("sim, real", [("sim-franka-rgbd", "franka-realsense"),
                                       ("sim-ur5e-tof", "ur5e-vl53l8cx")])
def test_real_cells_scan_with_what_their_simulated_twins_were_measured_with(sim, real):
    twin, cell = load_config(CONFIG_DIR / f"{sim}.yaml"), load_config(CONFIG_DIR / f"{real}.yaml")
    for section in ("vs", "vs_local", "vs_global"):
        assert getattr(cell.planners, section) == getattr(twin.planners, section), section
    assert cell.perception.occupancy == twin.perception.occupancy


def test_unknown_robot_model_names_field_and_allowed_values(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["arm"]["model"] = "kuka"
    with pytest.raises(ConfigError) as info:
        parse_config(data, file="cell.yaml")
    text = str(info.value)
    assert "cell.yaml" in text and "arm.model" in text
    assert "'panda'" in text and "'ur5e'" in text
    assert info.value.field == "arm.model"


def test_unknown_arm_type_lists_the_types(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["arm"]["type"] = "abb"
    with pytest.raises(ConfigError) as info:
        parse_config(data, file="cell.yaml")
    assert "arm" in str(info.value) and "'sim'" in str(info.value) and "'ur5e'" in str(info.value)


def test_unknown_field_is_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["safety"]["max_speed"] = 3
    with pytest.raises(ConfigError, match=r"safety\.max_speed"):
        parse_config(data, file="cell.yaml")


@pytest.mark.parametrize("name", ["x" * 65, "../cell", "cell a", ""])
def test_a_cell_name_the_store_cannot_key_is_refused(franka_cfg_data, name):
    data = copy.deepcopy(franka_cfg_data)
    data["name"] = name
    with pytest.raises(ConfigError) as info:
        parse_config(data, file="cell.yaml")
    assert info.value.field == "name"


def test_missing_safety_value_is_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    del data["safety"]["tcp_max_linear_mps"]
    with pytest.raises(ConfigError, match=r"safety\.tcp_max_linear_mps"):
        parse_config(data, file="cell.yaml")


def test_limit_above_robot_ceiling_is_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["safety"]["tcp_max_linear_mps"] = 5.0
    with pytest.raises(ConfigError) as info:
        parse_config(data, file="cell.yaml")
    assert info.value.field == "safety.tcp_max_linear_mps" and "at most" in str(info.value)


def test_home_joints_of_wrong_length_are_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["arm"]["home_joints_rad"] = [0.0] * 6
    with pytest.raises(ConfigError, match=r"arm\.home_joints_rad"):
        parse_config(data, file="cell.yaml")


def test_sim_mode_with_hardware_arm_is_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["arm"] = {"type": "franka", "host": "10.0.0.2", "relative_dynamics_factor": 0.1,
                   "velocity_hold_s": 0.05, "max_linear_mps": 0.1, "max_angular_rps": 0.5,
                   "payload": {"mass_kg": 0.3, "cog_m": [0.0, 0.0, 0.03]}, "torque_threshold_nm": 20.0,
                   "force_threshold_n": 30.0}
    with pytest.raises(ConfigError, match="mode 'sim'"):
        parse_config(data, file="cell.yaml")


def test_bad_yaml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("arm: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: line 2, column 1: not valid YAML: .* flow sequence at "
                                          r"line 1, column 6"):
        load_config(bad)
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "absent.yaml")


@pytest.mark.parametrize("text, where", [
    ("name: x\n  mode: sim\n", "line 2, column 7"),      # an indented key: mapping values not allowed
    ("name: x\nmode: \"sim\n", "line 3, column 1"),      # an unterminated string
    ("name: \x01\n", "character 7"),                     # a control character
])
def test_a_yaml_syntax_error_is_one_line_with_file_line_and_column(tmp_path, text, where):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    res = CliRunner().invoke(app, ["config", "check", str(bad)])
    assert res.exit_code == 1
    assert res.output.count("\n") == 1 and res.output.startswith(f"error: {bad}: {where}: not valid YAML: ")


@pytest.mark.parametrize("cell, path, value", [
    ("sim-franka-rgbd", ("safety", "tcp_max_linear_mps"), "0.25"),
    ("sim-franka-rgbd", ("safety", "barrier_margin_m"), True),
    ("sim-franka-rgbd", ("safety", "watchdog", "max_missed_deadlines"), "3"),
    ("sim-franka-rgbd", ("safety", "workspace", "max_m"), [0.85, "0.7", 1.1]),
    ("dryrun-ur5e-peer", ("arm", "max_linear_mps"), "0.1"),
])
def test_a_quoted_number_in_a_safety_field_is_refused(cell, path, value):
    data = yaml.safe_load((CONFIG_DIR / f"{cell}.yaml").read_text())
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(ConfigError, match=rf"{'.'.join(path)}.*: Input should be a valid (number|integer)"):
        parse_config(data, file="cell.yaml")


def test_integers_are_numbers_in_safety_fields(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["safety"]["workspace"]["max_m"] = [1, 1, 1]
    data["safety"]["watchdog"]["perception_max_age_s"] = 2
    cfg = parse_config(data, file="cell.yaml")
    assert cfg.safety.workspace.max_m == (1.0, 1.0, 1.0) and cfg.safety.watchdog.perception_max_age_s == 2.0


def test_cli_config_check(tmp_path, franka_cfg_data):
    runner = CliRunner()
    ok = runner.invoke(app, ["config", "check", str(CONFIG_DIR / "sim-franka-rgbd.yaml")])
    assert ok.exit_code == 0 and "ready: nothing left to measure" in ok.output
    assert "line:" not in ok.output
    lined = copy.deepcopy(franka_cfg_data)
    lined["line"] = {"initial_mode": "manual", "opcua": {"endpoint": "opc.tcp://127.0.0.1:4840/cell"}}
    (tmp_path / "line.yaml").write_text(yaml.safe_dump(lined))
    line = runner.invoke(app, ["config", "check", str(tmp_path / "line.yaml")])
    assert line.exit_code == 0
    assert ("line: starts in manual mode; driven over REST, OPC UA at opc.tcp://127.0.0.1:4840/cell "
            "(security sign-and-encrypt)") in line.output
    data = copy.deepcopy(franka_cfg_data)
    data["arm"]["model"] = "kuka"
    bad = tmp_path / "kuka.yaml"
    bad.write_text(yaml.safe_dump(data))
    res = runner.invoke(app, ["config", "check", str(bad)])
    assert res.exit_code == 1
    assert "arm.model" in res.output and "kuka.yaml" in res.output


def test_sensor_range_must_be_ordered(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["sensor"]["range_min_m"] = 2.0
    with pytest.raises(ConfigError, match=r"range_min_m 2\.0 must be below range_max_m 1\.5"):
        parse_config(data, file="cell.yaml")


@pytest.mark.parametrize("field, value, message", [
    ("xy_m", [5.0, 5.0], r"station\.xy_m: \[5\.0, 5\.0\] is off the table of safety\.collision\.table "
                         r"\(allowed: x in \[-0\.2, 1\], y in \[-0\.6, 0\.6\]\)"),
    ("xy_m", [0.45, float("inf")], r"station\.xy_m\[1\]: Input should be a finite number"),
    ("xy_m", [True, False], r"station\.xy_m\[0\]: Input should be a valid number"),
    ("xy_m", ["0.45", 0.0], r"station\.xy_m\[0\]: Input should be a valid number"),
    ("table_z_m", 5.0, r"station\.table_z_m: 5 m is not below the top of safety\.workspace "
                       r"\(allowed: below 1\.1 m\)"),
    ("table_z_m", float("nan"), r"station\.table_z_m: Input should be a finite number"),
])
def test_a_station_no_scan_can_use_is_refused(field, value, message):
    """Off the table, outside the workspace, not finite or not a number: each passed and failed the scan."""
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["station"][field] = value
    with pytest.raises(ConfigError, match=rf"^cell\.yaml: {message}"):
        parse_config(data, file="cell.yaml")


def test_a_station_off_the_simulated_table_or_the_workspace_is_refused(franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["sim"]["table_center_xy_m"] = [1.2, 0.0]  # the collision world's table still holds the station
    with pytest.raises(ConfigError, match=r"station\.xy_m: \[0\.45, 0\.0\] is off the table of sim "):
        parse_config(data, file="cell.yaml")
    data = copy.deepcopy(franka_cfg_data)
    data["safety"]["workspace"]["min_m"][0] = 0.5
    with pytest.raises(ConfigError, match=r"station\.xy_m: \[0\.45, 0\.0\] is outside safety\.workspace "
                                          r"\(allowed: x in \(0\.5, 0\.85\), y in \(-0\.7, 0\.7\)\)"):
        parse_config(data, file="cell.yaml")


def test_a_watchdog_that_tolerates_late_ticks_longer_than_old_perception_is_refused(franka_cfg_data):
    """100 Hz, 1.5 periods a miss, 3 s of perception age: at most 200 late ticks in a row (3 s)."""
    data = copy.deepcopy(franka_cfg_data)
    data["safety"]["watchdog"]["max_missed_deadlines"] = 200
    assert parse_config(data, file="cell.yaml").safety.watchdog.max_missed_deadlines == 200
    # 10 ticks of 1.1 periods at 100 Hz last 0.11 s exactly (9.999999999999998 in floating point)
    data["safety"]["watchdog"].update(deadline_factor=1.1, perception_max_age_s=0.11, max_missed_deadlines=10)
    assert parse_config(data, file="cell.yaml").safety.watchdog.max_missed_deadlines == 10
    data["safety"]["watchdog"].update(deadline_factor=1.5, perception_max_age_s=3.0,
                                      max_missed_deadlines=1000000)
    with pytest.raises(ConfigError, match=r"safety\.watchdog\.max_missed_deadlines: 1000000 late ticks .*"
                                          r"\(allowed: at most 200 "):
        parse_config(data, file="cell.yaml")


def test_an_empty_sensor_port_is_refused():
    data = yaml.safe_load((CONFIG_DIR / "ur5e-vl53l8cx.yaml").read_text())
    data["sensor"]["port"] = ""
    with pytest.raises(ConfigError, match=r"sensor\.port: .*the port is empty"):
        parse_config(data, file="cell.yaml")


def test_an_unknown_default_planner_fails_config_check_naming_the_registered_ones(tmp_path, franka_cfg_data):
    data = copy.deepcopy(franka_cfg_data)
    data["scan"]["planner"] = "nope"
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["config", "check", str(tmp_path / "cell.yaml")])
    assert res.exit_code == 1
    assert res.output == (f"error: {tmp_path / 'cell.yaml'}: scan.planner: 'nope' is no registered planner "
                          "(allowed: raster, lr-nbv, nbv, heu, vs-local, vs-global, vs-hybrid)\n")


def test_a_servo_rate_above_the_control_rate_fails_config_check(tmp_path, franka_cfg_data):
    """Every visual-servoing scan would refuse the file: config check says so, as the scan did."""
    data = copy.deepcopy(franka_cfg_data)
    data["planners"]["vs"]["servo_rate_hz"] = 2 * data["scan"]["control_rate_hz"]
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["config", "check", str(tmp_path / "cell.yaml")])
    assert res.exit_code == 1
    assert res.output == (f"error: {tmp_path / 'cell.yaml'}: planners.vs.servo_rate_hz 200 exceeds "
                          "scan.control_rate_hz 100\n")
    data["planners"]["vs"]["servo_rate_hz"] = data["scan"]["control_rate_hz"]
    assert parse_config(data, file="cell.yaml").planners.vs.servo_rate_hz == 100


def test_a_relative_zone_correction_is_read_from_the_cell_files_folder(tmp_path, monkeypatch):
    """``sensor.zone_correction: zones.json`` (calibration/README.md) names the file beside the cell file,
    wherever the command runs; the worker, given the parsed data, reads the same file."""
    cell_dir, elsewhere = tmp_path / "cell", tmp_path / "elsewhere"
    cell_dir.mkdir()
    elsewhere.mkdir()
    write_zone_correction(ZoneCorrection(resolution=8, offset_m=np.full(64, 0.001), noise_m=np.zeros(64)),
                          cell_dir / "zones.json")
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["sensor"]["zone_correction"] = "zones.json"
    (cell_dir / "cell.yaml").write_text(yaml.safe_dump(data))
    monkeypatch.chdir(elsewhere)
    cfg, parsed = load_config_data(Path("../cell/cell.yaml"))
    assert Path(cfg.sensor.zone_correction) == (cell_dir / "zones.json").resolve()
    assert parse_config(parsed, file="cell.yaml").sensor.zone_correction == cfg.sensor.zone_correction


@pytest.mark.parametrize("content, message", [
    (None, r"sensor\.zone_correction: .*zones\.json is not a file \(a relative path is taken from the cell "
           r"file's folder\)"),
    ("{}", r"zones\.json: sensor\.zone_correction: not a zone correction"),
])
def test_a_zone_correction_that_is_missing_or_unreadable_fails_config_check(tmp_path, content, message):
    if content is not None:
        (tmp_path / "zones.json").write_text(content)
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["sensor"]["zone_correction"] = "zones.json"
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["config", "check", str(tmp_path / "cell.yaml")])
    assert res.exit_code == 1 and res.output.count("\n") == 1
    assert re.search(message, res.output), res.output


@pytest.mark.parametrize("path, value, message", [
    (("mode",), "sometimes", "mode: Input should be 'sim', 'dry-run', 'real' or 'replay'"),
    (("arm", "type"), "kuka", "arm: Input tag 'kuka' found using 'type' does not match any of the expected "
                              "tags: 'sim', 'ur5e', 'franka', 'replay'"),
])
def test_the_allowed_values_are_named_once(franka_cfg_data, path, value, message):
    data = copy.deepcopy(franka_cfg_data)
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(ConfigError) as error:
        parse_config(data, file="cell.yaml")
    assert str(error.value) == f"cell.yaml: {message}"


@pytest.mark.parametrize("path, value", [
    (("service", "stop_confirm_timeout_s"), "1e9"),
    (("service", "shutdown_timeout_s"), True),
    (("service", "queue_max"), "16"),
    (("service", "max_upload_mb"), "50"),
    (("service", "retention", "days"), "90"),
])
def test_a_quoted_number_in_the_service_section_is_refused(franka_cfg_data, path, value):
    """As in the safety section: "1e9" was refused for perception_max_age_s and read for a timeout."""
    data = copy.deepcopy(franka_cfg_data)
    node = data
    for key in path[:-1]:
        node = node.setdefault(key, {})
    node[path[-1]] = value
    with pytest.raises(ConfigError, match=rf"{'.'.join(path)}: Input should be a valid (number|integer)"):
        parse_config(data, file="cell.yaml")


MM = r"; it looks like millimetres \({mm} mm is {m} m\)(;|$)"


@pytest.mark.parametrize("cell, path, value, message", [
    # millimetres in the metres of what the wrist carries: passed every check and went to the robot
    ("dryrun-ur5e-peer", ("arm", "tcp_offset"), [0.0, 40, 30, 0.0, 0.0, 0.0],
     r"arm\.tcp_offset\[1\]: 40 m is outside \[-0\.5, 0\.5\] m: the wrist tool lies within 0\.5 m of the "
     r"flange" + MM.format(mm=40, m=r"0\.04")),
    ("dryrun-ur5e-peer", ("arm", "tcp_offset"), [0.0, 0.04, 0.03, 0.0, 0.0, 90],
     r"arm\.tcp_offset\[5\]: 90 rad is outside \[-6\.2832, 6\.2832\] rad: .*; it looks like degrees "
     r"\(90 deg is 1\.5708 rad\)$"),
    ("dryrun-ur5e-peer", ("arm", "payload", "cog_m"), [0, 30, 20],
     r"arm\.payload\.cog_m\[1\]: 30 m is outside \[-0\.5, 0\.5\] m: .*" + MM.format(mm=30, m=r"0\.03")),
    ("franka-realsense", ("arm", "payload", "cog_m"), [30, 0.0, 0.03],
     r"arm\.payload\.cog_m\[0\]: 30 m is outside .*" + MM.format(mm=30, m=r"0\.03")),
    ("dryrun-ur5e-peer", ("mount", "xyz_m"), [0, 40, 30],
     r"mount\.xyz_m\[1\]: 40 m is outside \[-0\.5, 0\.5\] m: .*" + MM.format(mm=40, m=r"0\.04")),
    ("sim-ur5e-tof", ("sim", "true_mount"), {"xyz_m": [0.0, 0.04, 30]},
     r"sim\.true_mount\.xyz_m\[2\]: 30 m is outside .*" + MM.format(mm=30, m=r"0\.03")),
    # a length too long for metres and too short for millimetres: no unit is suggested
    ("dryrun-ur5e-peer", ("mount", "xyz_m"), [0.8, 0.0, 0.0],
     r"mount\.xyz_m\[0\]: 0\.8 m is outside \[-0\.5, 0\.5\] m: the wrist tool lies within 0\.5 m of the "
     r"flange$"),
    # radians in a degrees field
    ("dryrun-ur5e-peer", ("sensor", "fov_deg"), 0.785,
     r"sensor\.fov_deg: 0\.785 deg is outside \[10, 65\] deg: a multizone ToF sensor's square field of "
     r"view .*; it looks like radians \(0\.785 rad is 44\.9772 deg\)$"),
    ("ur5e-vl53l8cx", ("sensor", "fov_deg"), 0.785, r"sensor\.fov_deg: 0\.785 deg is outside .*radians"),
    ("sim-ur5e-tof", ("planners", "vs", "objective", "fov_deg"), 0.52,
     r"planners\.vs\.objective\.fov_deg: 0\.52 deg is outside \[5, 120\] deg: .*; it looks like radians"),
    # voxel sizes: from half a millimetre to a few centimetres
    ("dryrun-ur5e-peer", ("perception", "voxel_m"), 2.5,
     r"perception\.voxel_m: 2\.5 m is outside \[0\.0005, 0\.05\] m: a voxel's edge is half a millimetre "
     r"to a few centimetres" + MM.format(mm=r"2\.5", m=r"0\.0025")),
    ("sim-franka-rgbd", ("perception", "occupancy", "resolution_m"), 5,
     r"perception\.occupancy\.resolution_m: 5 m is outside .*" + MM.format(mm=5, m=r"0\.005")),
    ("sim-franka-rgbd", ("perception", "registration", "source_voxel_m"), 2.5,
     r"perception\.registration\.source_voxel_m: 2\.5 m is outside \[0, 0\.05\] m: .*"
     + MM.format(mm=r"2\.5", m=r"0\.0025")),
    ("dryrun-ur5e-peer", ("perception", "voxel_m"), float("nan"), r"perception\.voxel_m: nan m is outside"),
    # the safety section's places and sizes: a workspace or a plane in millimetres limits nothing
    ("sim-franka-rgbd", ("safety", "workspace", "max_m"), [850, 700, 1100],
     r"safety\.workspace\.max_m\[0\]: 850 m is outside \[-2, 2\] m: the cell lies within 2 m of the robot's "
     r"base" + MM.format(mm=850, m=r"0\.85")),
    ("sim-franka-rgbd", ("safety", "barrier_planes", 0, "point"), [750, 0.0, 0.0],
     r"safety\.barrier_planes\[0\]\.point\[0\]: 750 m is outside .*" + MM.format(mm=750, m=r"0\.75")),
    ("sim-ur5e-tof", ("safety", "collision", "tool", 0, "size_m"), [40, 40, 30],
     r"safety\.collision\.tool\[0\]\.size_m\[0\]: 40 m is outside \[0\.001, 2\] m: a size or a distance in "
     r"the cell is 1 mm to 2 m" + MM.format(mm=40, m=r"0\.04")),
    ("sim-ur5e-tof", ("safety", "collision", "tool", 0, "pose", "xyz_m"), [0.0, 0.04, 15],
     r"safety\.collision\.tool\[0\]\.pose\.xyz_m\[2\]: 15 m is outside .*" + MM.format(mm=15, m=r"0\.015")),
    # the sensor, the scan and the planners
    ("sim-ur5e-tof", ("sensor", "range_max_m"), 4000,
     r"sensor\.range_max_m: 4000 m is outside \[0\.001, 10\] m: .*" + MM.format(mm=4000, m="4")),
    ("sim-ur5e-tof", ("perception", "crop_box", "z_m"), [20, 1500],
     r"perception\.crop_box\.z_m\[0\]: 20 m is outside \[-10, 10\] m: .*" + MM.format(mm=20, m=r"0\.02")),
    ("sim-ur5e-tof", ("perception", "segmentation", "dbscan_eps_m"), 30,
     r"perception\.segmentation\.dbscan_eps_m: 30 m is outside \[0\.0001, 0\.2\] m: .*"
     + MM.format(mm=30, m=r"0\.03")),
    ("sim-ur5e-tof", ("scan", "standoff_m"), 400,
     r"scan\.standoff_m: 400 m is outside \[0\.05, 2\] m: .*" + MM.format(mm=400, m=r"0\.4")),
    ("sim-ur5e-tof", ("planners", "lrnbv", "view_distance_m"), [200, 600],
     r"planners\.lrnbv\.view_distance_m\[0\]: 200 m is outside .*" + MM.format(mm=200, m=r"0\.2")),
])
def test_a_length_or_angle_in_the_wrong_unit_is_refused_naming_the_likely_unit(tmp_path, cell, path, value,
                                                                               message):
    """Each of these was accepted by config check and doctor; the arm then jogged a TCP 40 m away, or a
    dry-run scan reached none of its views. The shipped value loads, the one in the wrong unit does not,
    through the loader that reads the file."""
    data = yaml.safe_load((CONFIG_DIR / f"{cell}.yaml").read_text())
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    bad = tmp_path / "cell.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(bad))}: {message}"):
        load_config(bad)


def test_config_check_refuses_a_tcp_offset_in_millimetres(tmp_path):
    text = (CONFIG_DIR / "dryrun-ur5e-peer.yaml").read_text()
    assert "tcp_offset: [0.0, 0.04, 0.03, " in text
    bad = tmp_path / "cell.yaml"
    bad.write_text(text.replace("tcp_offset: [0.0, 0.04, 0.03, ", "tcp_offset: [0.0, 40, 30, "))
    res = CliRunner().invoke(app, ["config", "check", str(bad)])
    assert res.exit_code == 1
    assert res.output.startswith(f"error: {bad}: arm.tcp_offset[1]: 40 m is outside [-0.5, 0.5] m")
    assert "it looks like millimetres (40 mm is 0.04 m)" in res.output


@pytest.mark.parametrize("line, message", [
    ({"opcua": {"endpoint": "opc.tcp://127.0.0.1:99999/cell"}},
     r"line\.opcua\.endpoint: Port out of range 0-65535$"),
    ({"dio": {}}, r"line\.dio needs the arm's trigger_input, busy_output, done_output$"),
])
def test_a_validators_refusal_reads_as_its_own_words(line, message):
    """A refusal of the cell's own validators read "line.opcua.endpoint: Value error, Port out of range
    0-65535", pydantic's prefix before the words, in `cell config check`, `cell serve` and `cell doctor`."""
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["line"] = line
    with pytest.raises(ConfigError, match=rf"^cell\.yaml: {message}"):
        parse_config(data, file="cell.yaml")
