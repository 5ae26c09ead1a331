"""Load and validate a cell's YAML file into ``CellConfig``.

Every problem becomes one ``ConfigError`` naming the file, the dotted field and, where the field takes
a fixed set of values, the allowed ones. Nothing is connected or moved before this passes.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError
from pydantic_core import ErrorDetails

from cell.config.models import CellConfig
from drivers.depth.config import SimToFConfig, VL53L8CXConfig
from drivers.depth.zone_correction import load_zone_correction
from drivers.errors import ConfigError
from drivers.robots import get_robot_model


def _field_path(loc: tuple[Any, ...]) -> str:
    parts: list[str] = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        elif parts:
            parts.append(f".{item}")
        else:
            parts.append(str(item))
    return "".join(parts)


def _allowed(error: ErrorDetails) -> str | None:
    """The values the field takes, unless the error's message lists them already (a ``Literal``'s or a
    type tag's: "Input should be 'sim', 'dry-run', ..." said them twice)."""
    ctx = error.get("ctx") or {}
    for key in ("expected", "expected_tags"):
        if key in ctx:
            return None if str(ctx[key]) in error["msg"] else str(ctx[key])
    return None


def _message(error: ErrorDetails) -> str:
    """The error's message, without the "Value error, " pydantic puts before the words of a validator's
    ``ValueError`` (the cell's own checks: "line.opcua.endpoint: Value error, Port out of range 0-65535")."""
    ctx = error.get("ctx") or {}
    if error["type"] == "value_error" and "error" in ctx:
        return str(ctx["error"])
    return error["msg"]


def _strip_tags(loc: tuple[Any, ...], data: Any) -> tuple[Any, ...]:
    """Drop the union tag pydantic puts after a discriminated field (``arm.sim.model`` -> ``arm.model``, a
    collision body's ``tool[0].box.size_m`` -> ``tool[0].size_m``)."""
    out: list[Any] = []
    node = data
    for item in loc:
        if isinstance(node, dict) and item not in node and item in (node.get("type"), node.get("shape")):
            continue
        out.append(item)
        node = node.get(item) if isinstance(node, dict) else (
            node[item] if isinstance(node, list) and isinstance(item, int) and item < len(node) else None)
    return tuple(out)


def _check_ceilings(cfg: CellConfig, file: str) -> None:
    """Refuse limits above the robot model's own maxima and home joints outside its range."""
    model = get_robot_model(cfg.arm.model)
    s = cfg.safety
    ceilings = {
        "safety.tcp_max_linear_mps": (s.tcp_max_linear_mps, model.tcp_max_linear_mps),
        "safety.tcp_max_angular_rps": (s.tcp_max_angular_rps, model.tcp_max_angular_rps),
        "safety.tcp_max_linear_acc_mps2": (s.tcp_max_linear_acc_mps2, model.tcp_max_linear_acc),
        "safety.tcp_max_angular_acc_rps2": (s.tcp_max_angular_acc_rps2, model.tcp_max_angular_acc),
        "safety.tcp_max_linear_jerk_mps3": (s.tcp_max_linear_jerk_mps3, model.tcp_max_linear_jerk),
        "safety.tcp_max_angular_jerk_rps3": (s.tcp_max_angular_jerk_rps3, model.tcp_max_angular_jerk),
    }
    for field, (value, ceiling) in ceilings.items():
        if value > ceiling:
            raise ConfigError(f"{value} is above the {model.name} ceiling", file=file, field=field,
                              allowed=f"at most {ceiling}")
    home = cfg.arm.home_joints_rad
    if home is not None:
        q = np.asarray(home, dtype=float)
        if q.shape != (model.n_joints,):
            raise ConfigError(f"has {q.size} values", file=file, field="arm.home_joints_rad",
                              allowed=f"{model.n_joints} joint angles [rad] for the {model.name}")
        if np.any(q < model.q_min) or np.any(q > model.q_max):
            raise ConfigError("is outside the joint limits", file=file, field="arm.home_joints_rad",
                              allowed=f"between {np.round(model.q_min, 4).tolist()} and "
                                      f"{np.round(model.q_max, 4).tolist()}")


def _on(xy: tuple[float, float], center: tuple[float, float], size: tuple[float, float]) -> bool:
    """Whether the point ``xy`` lies on the rectangle of ``center`` and ``size`` [m]."""
    return all(abs(p - c) <= s / 2.0 for p, c, s in zip(xy, center, size, strict=True))


def _check_station(cfg: CellConfig, file: str) -> None:
    """Refuse a station no scan can use: its centre off the table (the collision world's, and in sim and
    dry-run the simulated one the sensor renders) or outside the workspace's footprint, the table top at
    or above the workspace's top (no view above it: the scan's object then measured metres below it)."""
    station, safety = cfg.station, cfg.safety
    xy, top = station.xy_m, station.table_z_m
    tables = {"safety.collision.table": (safety.collision.table.center_xy_m, safety.collision.table.size_m)}
    if cfg.mode in ("sim", "dry-run"):
        tables["sim"] = (cfg.sim.table_center_xy_m, cfg.sim.table_size_m)
    for name, (center, size) in tables.items():
        if not _on(xy, center, size):
            raise ConfigError(f"{list(xy)} is off the table of {name}", file=file, field="station.xy_m",
                              allowed=f"x in [{center[0] - size[0] / 2:g}, {center[0] + size[0] / 2:g}], "
                                      f"y in [{center[1] - size[1] / 2:g}, {center[1] + size[1] / 2:g}]")
    lo, hi = safety.workspace.min_m, safety.workspace.max_m
    if not all(lo[i] < xy[i] < hi[i] for i in (0, 1)):
        raise ConfigError(f"{list(xy)} is outside safety.workspace", file=file, field="station.xy_m",
                          allowed=f"x in ({lo[0]:g}, {hi[0]:g}), y in ({lo[1]:g}, {hi[1]:g})")
    if not top < hi[2]:
        raise ConfigError(f"{top:g} m is not below the top of safety.workspace", file=file,
                          field="station.table_z_m", allowed=f"below {hi[2]:g} m")


def _check_watchdog(cfg: CellConfig, file: str) -> None:
    """Refuse a late-loop watchdog that in practice never fires. While the control loop is late the arm
    runs on its last command; a run of ``max_missed_deadlines`` late ticks lasts at least that many times
    ``deadline_factor`` control periods. It may not last longer than the perception watchdog lets the arm
    move on data that old (``perception_max_age_s``): a loop that does not run at all is no safer than
    perception that runs late."""
    watchdog = cfg.safety.watchdog
    period_s = 1.0 / cfg.scan.control_rate_hz
    # rounded before the floor: 0.11 s / (1.1 x 10 ms) is 9.999999999999998 in binary floating point
    most = math.floor(round(watchdog.perception_max_age_s / (watchdog.deadline_factor * period_s), 9))
    missed = watchdog.max_missed_deadlines
    if missed > most:
        lasts_s = missed * watchdog.deadline_factor * period_s
        raise ConfigError(f"{missed} late ticks in a row last {lasts_s:g} s or more, longer than "
                          "safety.watchdog.perception_max_age_s", file=file,
                          field="safety.watchdog.max_missed_deadlines",
                          allowed=f"at most {most} (perception_max_age_s / (deadline_factor / "
                                  "scan.control_rate_hz))")


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """A YAML syntax error on one line, positions 1-based: where the problem is, what it is, and where
    the construct it broke began."""
    if isinstance(exc, yaml.MarkedYAMLError) and exc.problem_mark is not None:
        mark, context = exc.problem_mark, exc.context_mark
        text = f"line {mark.line + 1}, column {mark.column + 1}: not valid YAML: {exc.problem}"
        if exc.context and context is not None:
            text += f" ({exc.context} at line {context.line + 1}, column {context.column + 1})"
        return text
    if isinstance(exc, yaml.reader.ReaderError):
        char = exc.character
        code = char if isinstance(char, int) else ord(char)
        return f"character {exc.position + 1}: not valid YAML: {exc.reason} (#x{code:04x})"
    return "not valid YAML: " + " ".join(str(exc).split())


def parse_config(data: Any, file: str = "<config>") -> CellConfig:
    """Validate already-parsed YAML data; ``file`` names the source in error messages."""
    if not isinstance(data, dict):
        raise ConfigError("the file must hold a mapping of fields", file=file)
    try:
        cfg = CellConfig.model_validate(data)
    except ValidationError as exc:
        problems = [(_field_path(_strip_tags(tuple(err["loc"]), data)), _message(err), _allowed(err))
                    for err in exc.errors()]
        if len(problems) == 1:
            field, msg, allowed = problems[0]
            raise ConfigError(msg, file=file, field=field, allowed=allowed) from None
        text = "; ".join(f"{f}: {m}" + (f" (allowed: {a})" if a else "") for f, m, a in problems)
        error = ConfigError(text, file=file)
        error.field = problems[0][0]
        raise error from None
    _check_ceilings(cfg, file)
    _check_station(cfg, file)
    _check_watchdog(cfg, file)
    return cfg


def load_config(path: str | Path) -> CellConfig:
    """Read and validate the cell file at ``path``."""
    return load_config_data(path)[0]


def _resolve_zone_correction(data: Any, folder: Path) -> None:
    """Take a relative ``sensor.zone_correction`` from the cell file's ``folder`` (in ``data``, so that a
    job's worker, which validates ``data`` again from another working directory, reads the same file).
    Anything that is not a path is left for the validation to name."""
    sensor = data.get("sensor") if isinstance(data, dict) else None
    name = sensor.get("zone_correction") if isinstance(sensor, dict) else None
    if isinstance(sensor, dict) and isinstance(name, str) and name:
        sensor["zone_correction"] = str(folder / Path(name).expanduser())


def _check_zone_correction(cfg: CellConfig, file: str) -> None:
    """The sensor's zone correction file exists and holds a correction for its zones (else the scan
    failed after making its job folder)."""
    if not isinstance(cfg.sensor, (VL53L8CXConfig, SimToFConfig)) or cfg.sensor.zone_correction is None:
        return
    where = Path(cfg.sensor.zone_correction)
    if not where.is_file():
        raise ConfigError(f"{where} is not a file (a relative path is taken from the cell file's folder)",
                          file=file, field="sensor.zone_correction")
    load_zone_correction(where, cfg.sensor.resolution)


def load_config_data(path: str | Path) -> tuple[CellConfig, Any]:
    """Read and validate the cell file at ``path``; returns it with its parsed YAML (which
    ``parse_config`` validates again elsewhere, e.g. in a job's worker process). Relative file names in
    it are made absolute, taken from the cell file's folder: ``sensor.zone_correction``."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError("no such file", file=str(p))
    try:
        data = yaml.safe_load(p.read_text())
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not a text file: byte {exc.start + 1} is not UTF-8", file=str(p)) from None
    except yaml.YAMLError as exc:
        raise ConfigError(_yaml_problem(exc), file=str(p)) from None
    _resolve_zone_correction(data, p.parent.resolve())
    cfg = parse_config(data, file=str(p))
    _check_zone_correction(cfg, str(p))
    return cfg, data
