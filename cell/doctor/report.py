"""All of ``cell doctor``'s checks for one cell file, in the order an engineer works through them: the
machine, the cell file, then the devices it names."""

from __future__ import annotations

from pathlib import Path

from cell.config.load import load_config
from cell.config.models import CellConfig
from cell.config.placeholders import find_placeholders
from cell.doctor import devices, machine
from cell.doctor.findings import Finding, Status
from cell.line.opcua_endpoint import ENDPOINT_FIELD, EndpointProblem, endpoint_problem
from cell.service.instance import Instance, instance_of, opcua_address
from drivers.arm.config import FrankaArmConfig, UR5eArmConfig
from drivers.depth.config import VL53L8CXConfig
from drivers.errors import CellError


def _extras(cfg: CellConfig, db_url: str | None) -> dict[str, str]:
    """The packages the cell file needs beyond the base install, each with the extra that installs it."""
    needed: dict[str, str] = {}
    if isinstance(cfg.arm, UR5eArmConfig):
        needed["ur-rtde"] = "ur5e"
    if isinstance(cfg.arm, FrankaArmConfig):
        needed["franky-control"] = "franka"
    if isinstance(cfg.sensor, VL53L8CXConfig):
        needed.update({"pyserial": "tof"} if cfg.sensor.port is not None else
                      {"circuitpython-vl53lxcx": "i2c", "adafruit-blinka": "i2c"})
    if db_url is not None and db_url.startswith("postgresql"):
        needed["psycopg"] = "postgres"
    return needed


def _cell_file(path: Path, cfg: CellConfig) -> Finding:
    left = find_placeholders(path.read_text())
    if not left:
        return Finding.ok("cell file", f"{path}: {cfg.name}, mode {cfg.mode}, nothing left to measure")
    names = ", ".join(p.field for p in left)
    fix = f"measure each, write it and delete its '# MEASURE:' mark (cell config check {path})"
    if cfg.mode == "real":
        return Finding.fail("cell file", f"still to measure: {names}", fix)
    return Finding.warn("cell file", f"still to measure: {names} (a {cfg.mode} cell runs meanwhile)", fix)


def run_checks(config_file: Path, data_dir: Path, host: str, port: int,
               db_url: str | None = None) -> list[Finding]:
    """Every check, in order; a cell file that does not load is one failure and ends the list's device
    part (there is nothing to check it against)."""
    found = [machine.python_version(), machine.kernels(), machine.system_libraries()]
    try:
        cfg = load_config(config_file)
    except CellError as exc:
        found += machine.packages({})
        found.append(Finding.fail("cell file", str(exc), f"fix it, then: cell config check {config_file}"))
        return found
    found += machine.packages(_extras(cfg, db_url))
    if cfg.calibration.board is not None:
        found.append(machine.board_support())
    found.append(_cell_file(config_file, cfg))
    found += [machine.clock_sync(), machine.cpu_governor()]
    if isinstance(cfg.arm, FrankaArmConfig):  # the arm whose 1 kHz loop runs at real-time priority
        found.append(machine.realtime_limits(required=cfg.arm.realtime == "enforce"))
    # run on a live cell (docs/deploy.md), the ports its own service holds are in use, and rightly so
    served = machine.serves_cell(host, port, data_dir)
    found += [machine.disk(data_dir), machine.port_free(host, port, served=served is not None)]
    found += machine.store(data_dir, db_url, host)
    opcua = cfg.line.opcua if cfg.line is not None else None
    if opcua is not None:
        problem = endpoint_problem(cfg.line)
        if problem is None:
            found.append(Finding.ok("line OPC UA port", f"{opcua.endpoint} is free"))
        else:
            found.append(_opcua_in_use(problem, instance_of(data_dir), served is not None, f"{host}:{port}"))
    if isinstance(cfg.sensor, VL53L8CXConfig) and cfg.sensor.port is not None:
        found.append(devices.serial_port(cfg.sensor.port))
    if isinstance(cfg.arm, UR5eArmConfig):
        found += devices.ur_controller(cfg.arm.host)
    elif isinstance(cfg.arm, FrankaArmConfig):
        found.append(devices.franka_controller(cfg.arm.host))
    return found


def _opcua_in_use(problem: EndpointProblem, written: Instance | None, answered: bool,
                  service: str) -> Finding:
    """The finding for the line's OPC UA endpoint that cannot be listened on (``problem``), given what
    the data folder's service wrote at its latest start (``written``) and whether it ``answered`` on the
    HTTP address ``service`` (doctor's ``--host``:``--port``): fine when it answered and wrote that it listens
    there (``cell serve`` checked it free), not when it listens on another (the cell file changed since it
    started). When it wrote that it listens there but did not answer, it may run on another HTTP port than
    doctor was given (``cell serve --port``): the finding says so, rather than only blaming another
    program."""
    endpoint, reason, detail = problem.endpoint, problem.reason, str(problem)
    if written is not None and written.opcua is not None and reason == machine.IN_USE:
        here = written.opcua == opcua_address(endpoint)
        if answered and here:
            return Finding.ok("line OPC UA port", f"{endpoint} is in use by this cell's running service")
        if answered:
            host, port = written.opcua
            detail += (f" (this cell's running service listens for OPC UA on {host}:{port}: the cell file "
                        "changed since it started, or another program holds this port)")
        elif here:
            detail += (f" (this data folder's service wrote at its latest start that it listens here, but "
                        f"none answers on {service}: if it runs, give doctor its --host and --port; else "
                        "another program holds this port)")
    setting = f"{ENDPOINT_FIELD}, and the PLC's configuration"
    in_use = (f"stop the program that holds it, or change {ENDPOINT_FIELD} (and the PLC's configuration); "
              "after a change of the cell file, restart cell serve")
    return Finding.fail("line OPC UA port", detail, machine.listen_fix(reason, problem.host, in_use, setting,
                                                                       setting))


def failed(found: list[Finding]) -> bool:
    return any(f.status is Status.FAIL for f in found)
