"""``cell doctor``: ok against the RTDE controller peer, a pseudo-terminal as the sensor's port and the
Franka connect peer; each failure class reported with its fix (an absent robot, port or package, no
permission, broken kernels, a full disk, a taken port, placeholders, real-time limits)."""

from __future__ import annotations

import errno
import grp
import os
import re
import shutil
import socket
import stat
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from cell.cli.main import app
from cell.doctor import devices, machine
from cell.doctor.findings import Status
from cell.service.keys import create_key
from cell.service.store import open_data_store, sqlite_url
from drivers.arm.franka import client_version
from drivers.file_access import user_name
from drivers.hosts import INVALID_HOST_NAME
from tests.conftest import CONFIG_DIR, UR5E
from tests.franka_connect_peer import FrankaConnectPeer
from tests.loopback import free_loopback
from tests.rtde_peer import ControllerPeer
from tests.service_process import ServedCell, free_port, opcua_cell_file
from tests.test_arm_cli import TEMPLATE, peer_cell_file


@pytest.fixture(scope="module")
def peer() -> Iterator[ControllerPeer]:
    p = ControllerPeer()
    yield p
    p.stop()


@pytest.fixture
def pty_port() -> Iterator[str]:
    controller, device = os.openpty()
    yield os.ttyname(device)
    os.close(device)
    os.close(controller)


def _cell(tmp_path: Path, host: str, port: str, template: Path = TEMPLATE, **arm: object) -> Path:
    """``template`` (its marks dropped, as measured) with the robot at ``host`` and the sensor on ``port``."""
    if template == TEMPLATE:
        template = peer_cell_file(template, host, tmp_path)
    data = yaml.safe_load(template.read_text())
    data["arm"].update(host=host, **arm)
    if "port" in data["sensor"]:
        data["sensor"]["port"] = port
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _doctor(cell_file: Path, tmp_path: Path, *extra: str,
            port: int | None = None) -> tuple[int, dict[str, tuple[str, str]]]:
    """Exit code and, per check, (status, the detail and fix lines); the service port ``port`` (default a
    free one)."""
    res = CliRunner().invoke(app, ["doctor", "--config", str(cell_file), "--data-dir", str(tmp_path / "data"),
                                   "--port", str(free_port() if port is None else port), *extra])
    checks: dict[str, tuple[str, str]] = {}
    name = ""
    for line in res.output.splitlines():
        match = re.match(r"(ok  |warn|FAIL)  (.+?)\s{2,}(.*)$", line)
        if match:
            name = match.group(2).strip()
            checks[name] = (match.group(1).strip().lower(), match.group(3))
        elif line.strip().startswith("fix:") and name:
            checks[name] = (checks[name][0], checks[name][1] + " " + line.strip())
    assert checks, res.output
    return res.exit_code, checks


def test_ok_against_the_controller_peer_and_a_pty(peer, pty_port, tmp_path):
    code, checks = _doctor(_cell(tmp_path, peer.host, pty_port), tmp_path)
    assert checks["robot RTDE"][0] == "ok" and "protocol 2" in checks["robot RTDE"][1]
    assert checks["robot software"] == ("ok", "URSoftware 5.15.0.0 (Jan 01 2024)")
    assert checks["robot remote control"][0] == "ok"
    assert checks["serial port"] == ("ok", f"{pty_port} opens")
    assert checks["cell file"][0] == "ok" and checks["package ur-rtde"][0] == "ok"
    assert checks["compiled kernels"][0] == "ok" and checks["service port"][0] == "ok"
    assert not [name for name, (status, _) in checks.items() if status == "fail"]
    assert code == 0


def test_a_pendant_in_local_mode_is_a_warning_with_its_fix(pty_port, tmp_path):
    local = ControllerPeer(remote_control=False)
    try:
        code, checks = _doctor(_cell(tmp_path, local.host, pty_port), tmp_path)
    finally:
        local.stop()
    status, text = checks["robot remote control"]
    assert status == "warn" and "fix: on the pendant" in text and code == 0


def test_no_robot_no_port_and_a_taken_service_port_fail_with_their_fixes(tmp_path):
    nobody = free_loopback([30004, 29999])
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        code, checks = _doctor(_cell(tmp_path, nobody, "/dev/no-such-board"), tmp_path,
                               port=taken.getsockname()[1])
    assert code == 1
    for name in ("robot RTDE", "robot dashboard"):
        assert checks[name][0] == "fail" and "fix: check the robot is on" in checks[name][1]
    assert checks["serial port"][0] == "fail" and "`cell deploy files`" in checks["serial port"][1]
    assert checks["service port"][0] == "fail" and "ss -ltnp" in checks["service port"][1]
    assert checks["service port"][1].endswith("stop it, or choose another port")


def test_a_host_not_this_machines_or_a_port_of_the_systems_is_not_blamed_on_another_program(
        tmp_path, monkeypatch):
    """An OPC UA endpoint on the PLC network's address of another PC, a --host that does not resolve, or a
    port below 1024 for a user who may not take one: each was "another program has it: stop it"."""
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["line"] = {"opcua": {"endpoint": "opc.tcp://192.0.2.1:4840/cell"}}  # TEST-NET-1: no machine's
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    code, checks = _doctor(cell_file, tmp_path, "--host", "no-such-host.invalid")
    assert code == 1
    status, text = checks["line OPC UA port"]
    assert status == "fail" and "Cannot assign requested address" in text, text
    assert text.endswith("fix: 192.0.2.1 is no name or address of this machine (ip -brief address lists "
                         "them; 0.0.0.0 is every one): correct it (line.opcua.endpoint, and the PLC's "
                         "configuration)"), text
    status, text = checks["service port"]
    assert status == "fail" and text.endswith(
        "fix: no-such-host.invalid is no name or address of this machine (ip -brief address lists them; "
        "0.0.0.0 is every one): correct it (cell serve --host)"), text
    # the tests run as root, who may take any port: the refusal a service user meets, as bind(2) words it
    monkeypatch.setattr(machine, "listen_problem", lambda host, port: os.strerror(errno.EACCES))
    code, checks = _doctor(cell_file, tmp_path, port=80)
    assert checks["service port"] == ("fail", f"cannot listen on 127.0.0.1:80: {os.strerror(errno.EACCES)} "
                                      "fix: a port below 1024 is the system's: choose one from 1024 up (cell "
                                      "serve --port)")


def test_an_endpoint_host_no_resolver_takes_is_a_finding_and_a_refusal_not_a_traceback(tmp_path):
    """A host name with a label of over 63 characters (a pasted name, two joined by mistake): getaddrinfo
    raised UnicodeError, and doctor and cell serve ended with a traceback. Doctor now fails the check with
    the host's fix (its reason holds a colon: the fix is chosen by the check's reason, not cut from the
    message), and cell serve refuses to start with the same words."""
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    host = "a" * 64 + ".example"
    data["line"] = {"opcua": {"endpoint": f"opc.tcp://{host}:4840/cell"}}
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    code, checks = _doctor(cell_file, tmp_path)
    assert code == 1
    assert checks["line OPC UA port"] == (
        "fail", f"cannot listen on opc.tcp://{host}:4840/cell: {INVALID_HOST_NAME} fix: {host} is no name or "
        "address of this machine (ip -brief address lists them; 0.0.0.0 is every one): correct it "
        "(line.opcua.endpoint, and the PLC's configuration)")
    res = CliRunner().invoke(app, ["serve", "--config", str(cell_file), "--data-dir", str(tmp_path / "data"),
                                   "--port", str(free_port())])
    assert res.exit_code == 1, res.output
    assert f"line.opcua.endpoint: cannot listen on opc.tcp://{host}:4840/cell: {INVALID_HOST_NAME}" \
        in res.output, res.output
    assert not (tmp_path / "data").exists()  # refused before the store was made


def test_the_ports_the_cells_running_service_holds_are_ok_and_another_programs_fail(tmp_path):
    """Run on a live cell (docs/deploy.md, e.g. after store damage), doctor failed both ports its own
    service held: 'Address already in use', 'fix: another program has it'."""
    cell_file, opcua_port = opcua_cell_file(tmp_path, UR5E)
    endpoint = f"opc.tcp://127.0.0.1:{opcua_port}/cell"
    with ServedCell(cell_file, tmp_path / "data") as cell:
        code, checks = _doctor(cell_file, tmp_path, port=cell.port)
        # a cell of the same name with another data dir (a copied cell file): that service is not its own
        (tmp_path / "copy").mkdir()
        copy_code, copy_checks = _doctor(cell_file, tmp_path / "copy", port=cell.port)
        # doctor given another --port than the service's (cell serve --port): the OPC UA port its data folder
        # says the service holds failed as another program's, with nothing about the port doctor asked
        asked = free_port()
        other_code, other_checks = _doctor(cell_file, tmp_path, port=asked)
        # its cell file changed since it started, to an OPC UA port another program holds: that port is not
        # the service's, though the service answers on its HTTP port (it was taken for the service's)
        moved = tmp_path / "moved.yaml"
        data = yaml.safe_load(cell_file.read_text())
        with socket.socket() as other:
            other.bind(("127.0.0.1", 0))
            other.listen(1)
            data["line"]["opcua"]["endpoint"] = f"opc.tcp://127.0.0.1:{other.getsockname()[1]}/cell"
            moved.write_text(yaml.safe_dump(data))
            moved_code, moved_checks = _doctor(moved, tmp_path, port=cell.port)
    status, text = moved_checks["line OPC UA port"]
    assert status == "fail" and moved_code == 1, moved_checks
    assert f"this cell's running service listens for OPC UA on 127.0.0.1:{opcua_port}" in text, text
    assert moved_checks["service port"][0] == "ok"
    assert checks["service port"] == ("ok", f"127.0.0.1:{cell.port} is in use by this cell's running service")
    assert checks["line OPC UA port"] == ("ok", f"{endpoint} is in use by this cell's running service")
    assert code == 0, checks
    assert copy_checks["service port"][0] == copy_checks["line OPC UA port"][0] == "fail" and copy_code == 1
    assert "this data folder's service" not in copy_checks["line OPC UA port"][1]
    status, text = other_checks["line OPC UA port"]
    assert status == "fail" and other_code == 1, other_checks
    assert (f"(this data folder's service wrote at its latest start that it listens here, but none answers "
            f"on 127.0.0.1:{asked}: if it runs, give doctor its --host and --port; else another program "
            "holds this port)") in text, text
    # the same ports, held by another program, still fail
    with socket.socket() as service, socket.socket() as opcua:
        for held, at in ((service, cell.port), (opcua, opcua_port)):
            held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # past the service's TIME_WAITs
            held.bind(("127.0.0.1", at))
            held.listen(1)
        code, checks = _doctor(cell_file, tmp_path, port=cell.port)
    assert checks["service port"][0] == "fail" and "another program has it" in checks["service port"][1]
    assert checks["line OPC UA port"][0] == "fail", checks["line OPC UA port"]
    assert "Address already in use" in checks["line OPC UA port"][1] and code == 1


def _port_of(monkeypatch, port: str, uid: int, gid: int, mode: int) -> None:
    """``port`` seen as owned by ``uid``:``gid`` with permissions ``mode``, and closed to this user."""
    real_stat, real_access = os.stat, os.access

    def fake_stat(path, *args, **kwargs):
        st = real_stat(path, *args, **kwargs)
        if path != port:
            return st
        return os.stat_result((stat.S_IFCHR | mode, st.st_ino, st.st_dev, st.st_nlink, uid, gid, st.st_size,
                               int(st.st_atime), int(st.st_mtime), int(st.st_ctime)))

    monkeypatch.setattr(os, "stat", fake_stat)
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: path != port and real_access(path, mode, **kw))


def test_a_port_of_a_group_this_user_is_not_in_names_the_group_and_the_user(pty_port, monkeypatch):
    """The fix said `usermod -aG dialout $USER`, a literal $USER under sudo -u cell."""
    dialout = grp.getgrnam("dialout").gr_gid
    _port_of(monkeypatch, pty_port, 0, dialout, 0o660)
    found = devices.serial_port(pty_port)
    assert found.status is Status.FAIL
    assert f"root:dialout with mode 0660, and user {user_name()}" in found.detail
    assert found.fix is not None and found.fix.startswith(f"sudo usermod -aG dialout {user_name()} ")


@pytest.mark.parametrize(("gid", "mode"), [(0, 0o660), (5, 0o620)])
def test_a_port_no_group_but_roots_may_open_is_given_the_udev_rule_never_root(pty_port, monkeypatch, gid,
                                                                             mode):
    """/dev/ttyS0 root:root (or a tty the group may only write) gave `sudo usermod -aG root $USER`."""
    _port_of(monkeypatch, pty_port, 0, gid, mode)
    found = devices.serial_port(pty_port)
    assert found.status is Status.FAIL and found.fix is not None
    assert "usermod" not in found.fix and "-aG root" not in found.fix
    assert "cell deploy files DIR, then sudo cp DIR/udev/99-vl53l8cx.rules /etc/udev/rules.d/" in found.fix
    assert found.fix.endswith("sensor.port: /dev/vl53l8cx")


def test_a_data_folder_this_user_may_not_write_names_the_user_to_give_it_to(tmp_path, monkeypatch):
    """The fix said `sudo chown -R $USER ...` though doctor runs as the service's user."""
    data = tmp_path / "data"
    data.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: Path(path) != data and real_access(path, mode,
                                                                                                  **kw))
    found = machine.disk(data)
    assert found.status is Status.FAIL and f"user {user_name()} may not write in it" in found.detail
    assert found.fix is not None and found.fix.startswith(f"chmod u+rwx {data}")
    assert "$USER" not in found.fix
    # not made yet, in a folder of the system's: the data folder is made for the user, that one not given
    found = machine.disk(data / "cell")
    assert found.status is Status.FAIL and f"folder {data} belongs to" in found.detail
    assert found.fix is not None and found.fix.startswith(f"sudo install -d -o {user_name()} -m 0750 "
                                                          f"{data / 'cell'}")


def test_broken_kernels_a_missing_extra_and_a_full_disk_fail_with_their_fixes(peer, pty_port, tmp_path,
                                                                             monkeypatch):
    real_import, real_version = machine.importlib.import_module, machine.metadata.version

    def no_kernel(name: str):
        if name == "cell.planning.vs._objective":
            raise ImportError("undefined symbol: GOMP_parallel")
        return real_import(name)

    def no_rtde(name: str) -> str:
        if name == "ur-rtde":
            raise machine.metadata.PackageNotFoundError(name)
        return real_version(name)

    monkeypatch.setattr(machine.importlib, "import_module", no_kernel)
    monkeypatch.setattr(machine.metadata, "version", no_rtde)
    full = shutil._ntuple_diskusage(10**12, 10**12, 5 * 10**8)  # 0.5 GB free
    monkeypatch.setattr(machine.shutil, "disk_usage", lambda _: full)
    code, checks = _doctor(_cell(tmp_path, peer.host, pty_port), tmp_path)
    assert code == 1
    assert checks["compiled kernels"][0] == "fail" and "GOMP_parallel" in checks["compiled kernels"][1]
    rtde = checks["package ur-rtde"]
    assert rtde[0] == "fail" and "pip install 'cell[ur5e]'" in rtde[1]
    assert checks["disk"][0] == "fail" and "service.retention" in checks["disk"][1]


def test_placeholders_and_a_bad_cell_file_fail(peer, tmp_path):
    template = CONFIG_DIR / "ur5e-vl53l8cx.yaml"
    code, checks = _doctor(template, tmp_path)
    assert code == 1 and checks["cell file"][0] == "fail" and "arm.host" in checks["cell file"][1]
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nmode: sometimes\n")
    code, checks = _doctor(bad, tmp_path)
    assert code == 1 and checks["cell file"][0] == "fail" and "cell config check" in checks["cell file"][1]


def test_an_unknown_default_planner_fails_the_cell_file(tmp_path):
    data = yaml.safe_load((CONFIG_DIR / "sim-ur5e-tof.yaml").read_text())
    data["scan"]["planner"] = "nope"
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    code, checks = _doctor(tmp_path / "cell.yaml", tmp_path)
    assert code == 1 and checks["cell file"][0] == "fail"
    assert "scan.planner: 'nope' is no registered planner (allowed: raster, " in checks["cell file"][1]


def test_the_franka_handshake_and_its_real_time_limits(tmp_path, monkeypatch):
    franka = CONFIG_DIR / "franka-realsense.yaml"
    good = FrankaConnectPeer(client_version())
    old = FrankaConnectPeer(client_version() - 1)
    try:
        _, checks = _doctor(_cell(tmp_path, good.host, "", franka), tmp_path)
        assert checks["robot FCI"][0] == "ok" and checks["package franky-control"][0] == "ok"
        _, checks = _doctor(_cell(tmp_path, old.host, "", franka), tmp_path)
        assert checks["robot FCI"][0] == "fail" and "franky-control that matches" in checks["robot FCI"][1]
    finally:
        good.stop()
        old.stop()
    monkeypatch.setattr(machine.os, "geteuid", lambda: 1000)
    monkeypatch.setattr(machine.resource, "getrlimit", lambda _: (0, 0))
    _, checks = _doctor(_cell(tmp_path, free_loopback([1337]), "", franka, realtime="enforce"), tmp_path)
    # the limits.d lines with the user's name (was: 'the cell's user - rtprio 99')
    who = user_name(1000)
    assert checks["real-time"][0] == "fail"
    assert f"'{who} - rtprio 99' '{who} - memlock unlimited' | sudo tee /etc/security/limits.d/cell.conf" \
        in checks["real-time"][1]
    _, checks = _doctor(_cell(tmp_path, free_loopback([1337]), "", franka, realtime="ignore"), tmp_path)
    assert checks["real-time"][0] == "warn"


@pytest.mark.parametrize("cell_file", ["sim-ur5e-tof.yaml", "sim-franka-rgbd.yaml", "ur5e-vl53l8cx.yaml"])
def test_only_a_franka_cell_is_checked_for_real_time_limits(tmp_path, monkeypatch, cell_file):
    """A UR5e or simulated cell was warned that it may not use priority 99, which only libfranka needs."""
    monkeypatch.setattr(machine.os, "geteuid", lambda: 1000)
    monkeypatch.setattr(machine.resource, "getrlimit", lambda _: (0, 0))
    _, checks = _doctor(CONFIG_DIR / cell_file, tmp_path)
    assert "real-time" not in checks


def test_a_franka_cell_without_franky_fails_its_fci_check_with_the_extra_to_install(tmp_path, monkeypatch):
    """The Franka's driver loads only for its own check; without franky that check fails, not doctor."""
    monkeypatch.setitem(sys.modules, "franky", None)  # None in sys.modules: the import raises
    monkeypatch.delitem(sys.modules, "drivers.arm.franka")
    code, checks = _doctor(_cell(tmp_path, free_loopback([1337]), "", CONFIG_DIR / "franka-realsense.yaml"),
                           tmp_path)
    assert code == 1 and checks["robot FCI"][0] == "fail"
    detail = checks["robot FCI"][1]
    assert "does not load" in detail and "pip install 'cell[franka]'" in detail


def test_without_opencv_a_cell_with_a_board_is_warned_with_the_extra_to_install(monkeypatch):
    """The ChArUco board's calibration needs OpenCV, which a venv with the hardware extras alone lacks."""
    assert machine.board_support().status is Status.OK
    monkeypatch.setitem(sys.modules, "cv2", None)  # None in sys.modules: the import raises
    found = machine.board_support()
    assert found.status is Status.WARN and found.fix == "pip install 'cell[calibration]'"
    assert "cell calibrate mount --target charuco" in found.detail


SIM_CELL = CONFIG_DIR / "sim-ur5e-tof.yaml"


def test_a_data_dir_that_is_a_file_fails(tmp_path):
    """cell serve cannot keep its jobs and store in a regular file; doctor said 0 failures."""
    (tmp_path / "data").write_text("")
    code, checks = _doctor(SIM_CELL, tmp_path)
    assert code == 1 and checks["disk"][0] == "fail" and "is not a folder" in checks["disk"][1]
    # the store check said "cannot read which store the service of DATA uses (DATA/store-url): Not a
    # directory" and to run doctor with another store (--db, CELL_DB), which no store would have fixed
    data = tmp_path / "data"
    assert checks["job store"] == ("fail", f"none: --data-dir {data} is not a folder fix: give --data-dir a "
                                   "folder (or a name not taken)")


def test_an_unreachable_store_fails_without_showing_its_password(tmp_path):
    """Only the psycopg package was checked; cell serve then failed to open the store."""
    url = f"postgresql+psycopg://cell:s3cret-pw@127.0.0.1:{free_port()}/cells"
    code, checks = _doctor(SIM_CELL, tmp_path, "--db", url)
    status, text = checks["job store"]
    assert code == 1 and status == "fail" and "cell:***@127.0.0.1" in text and "pg_isready" in text
    assert "s3cret-pw" not in text


def test_listening_beyond_loopback_needs_an_api_key_in_the_store(tmp_path):
    """cell serve refuses --host 0.0.0.0 with no API key; doctor said 0 failures. The store is read, never
    made or migrated."""
    code, checks = _doctor(SIM_CELL, tmp_path, "--host", "0.0.0.0")
    assert code == 1 and checks["remote access"][0] == "fail"
    assert "cell keys create --role admin --data-dir" in checks["remote access"][1]
    assert checks["job store"][0] == "ok" and not (tmp_path / "data").exists()
    store = open_data_store(tmp_path / "data", sqlite_url(tmp_path / "data"))
    try:
        create_key(store, "admin", "admin-1")
    finally:
        store.close()
    code, checks = _doctor(SIM_CELL, tmp_path, "--host", "0.0.0.0")
    assert checks["remote access"][0] == "ok" and "1 API keys" in checks["job store"][1]
    assert checks["job store"][0] == "ok"


def test_without_a_cell_file_doctor_checks_the_embedded_cell_as_serve_runs_it(tmp_path):
    """--config was required, though cell serve and cell scan run the shipped sim cell without it."""
    res = CliRunner().invoke(app, ["doctor", "--data-dir", str(tmp_path / "data"),
                                   "--port", str(free_port())])
    assert res.exit_code == 0, res.output
    assert re.search(r"^ok\s+cell file\s+.*sim-franka-rgbd\.yaml: sim-franka-rgbd, mode sim", res.output,
                     re.MULTILINE), res.output


def test_the_cpu_governor_is_read_from_sysfs(tmp_path):
    for cpu, governor in (("cpu0", "performance"), ("cpu1", "powersave")):
        (tmp_path / cpu / "cpufreq").mkdir(parents=True)
        (tmp_path / cpu / "cpufreq" / "scaling_governor").write_text(governor + "\n")
    slow = machine.cpu_governor(tmp_path)
    assert slow.status is Status.WARN and "powersave" in slow.detail and "cpupower" in (slow.fix or "")
    (tmp_path / "cpu1" / "cpufreq" / "scaling_governor").write_text("performance\n")
    assert machine.cpu_governor(tmp_path).status is Status.OK
    assert machine.cpu_governor(tmp_path / "none").status is Status.OK
