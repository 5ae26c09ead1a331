"""``cell sensor``: commission a depth sensor, emulate a VL53L8CX bridge, re-run a recorded job offline.

- ``cell sensor check --config FILE`` reads frames for a few seconds (or ``--frames N``) from the cell's
  sensor and prints the frame rate, the share of valid zones (pixels), the link's CRC errors and sequence
  gaps, and per-zone noise (see :mod:`drivers.depth.check`); ``--port`` overrides a VL53L8CX's port.
- ``cell sensor emulate`` serves the bridge protocol on a pseudo-terminal (or ``--socket HOST:PORT``),
  with frames of the simulated ToF sensor and optional injected faults, until Ctrl-C.
- ``cell sensor replay JOB_DIR`` plays a job folder's frames and poses through the replay sensor and the
  read-only replay arm into the perception pipeline of the job's cell file, and writes the cloud it
  rebuilds as ``cloud_replay.ply`` beside the recorded ``cloud.ply`` (or in ``--out DIR``).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Annotated, NamedTuple

import numpy as np
import typer
from rich.console import Console
from scipy.spatial import cKDTree

from cell.cli.commands import command_group
from cell.cli.errors import fail, print_warning
from cell.config import load_config
from cell.config.models import CellConfig
from cell.jobs.rebuild import check_job_dir, output_folder
from cell.jobs.replay import recorded_job
from cell.jobs.runner import job_generators
from cell.perception.cloud import read_ply, write_ply
from cell.perception.pipeline import PerceptionPipeline
from cell.templates import template_path
from drivers.arm.replay import ReplayArm
from drivers.clock import SimClock
from drivers.depth.check import CheckReport, SensorCheck
from drivers.depth.config import VL53L8CX_VALID_STATUSES, VL53L8CXConfig
from drivers.depth.replay import JobRecording, ReplaySensor
from drivers.depth.vl53l8cx.emulator import EmulatorFaults, SimToFSource, VL53L8CXEmulator
from drivers.depth.vl53l8cx.serial_driver import LinkStats, VL53L8CXSerial
from drivers.errors import CellError, DriverError, JobError
from drivers.factory import make_sensor
from drivers.robots import get_robot_model

sensor_app = command_group(help="Depth sensors: commissioning check, VL53L8CX bridge emulator, job replay.",
                           no_args_is_help=True)
console = Console(soft_wrap=True, highlight=False)
REPLAY_CLOUD = "cloud_replay.ply"
"""The cloud ``cell sensor replay`` writes, in the job folder or ``--out``."""


PORT_HINT = ("; is the bridge board plugged in, and is sensor.port its port? (the udev rule of `cell deploy "
             "files` makes it /dev/vl53l8cx; --port tries another; `cell doctor --config FILE` checks it)")
"""Added to the error of a VL53L8CX bridge board's serial device that does not open (not to a pyserial URL
such as socket://, which is no board plugged in)."""


def _int_set(text: str) -> frozenset[int]:
    try:
        return frozenset(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated frame indices, got {text!r}") from None


# -- check -----------------------------------------------------------------------------------------------
def _print_report(report: CheckReport, link: LinkStats | None,
                  valid_statuses: tuple[int, ...] | None) -> None:
    rate = f"{report.rate_hz:.1f} Hz" if np.isfinite(report.rate_hz) else "- Hz"
    device = f" (device clock {report.device_rate_hz:.1f} Hz)" if report.device_rate_hz else ""
    console.print(f"frames: {report.frames} in {report.duration_s:.2f} s, {rate}{device}", markup=False)
    what = (f"valid zones (statuses {', '.join(map(str, valid_statuses))})" if valid_statuses is not None
            else "pixels with depth")
    console.print(f"{what}: {100.0 * report.valid_share:.1f} %", markup=False)
    if link is not None:
        console.print(f"CRC errors: {link.crc_errors}", markup=False)
        console.print(f"sequence gaps: {link.gaps} ({link.lost} frames lost)", markup=False)
        console.print(f"link: {link.bytes_read} bytes read, {link.ranging_frames} ranging frames received "
                      f"({link.skipped} skipped for a newer one), {link.bad_headers} bad headers, "
                      f"{link.malformed} malformed, {link.duplicates} duplicates, {link.restarts} restarts, "
                      f"{link.bytes_discarded} bytes skipped", markup=False)
    if report.zone_noise_m is not None:
        noise_mm = report.zone_noise_m * 1e3
        console.print("per-zone noise [mm] (std over the frames, row 0 = top of the view):", markup=False)
        for row in noise_mm:
            cells = ("   -  " if not np.isfinite(v) else f"{v:6.1f}" for v in row)
            console.print(" ".join(cells), markup=False)
        finite = noise_mm[np.isfinite(noise_mm)]
        median = f"{np.median(finite):.1f} mm" if finite.size else "-"
        console.print(f"median zone noise: {median}", markup=False)


@sensor_app.command()
def check(
    config: Annotated[Path, typer.Option("--config", help="cell file whose sensor to check")],
    seconds: Annotated[float, typer.Option(help="how long to read frames [s], above 0")] = 3.0,
    frames: Annotated[int | None, typer.Option(min=1, help="read this many frames instead of --seconds")]
    = None,
    port: Annotated[str | None, typer.Option(help="VL53L8CX: pyserial URL replacing sensor.port")] = None,
) -> None:
    """Read frames from a cell's sensor and print commissioning figures; fails when it read none."""
    if not 0.0 < seconds < math.inf:
        raise typer.BadParameter(f"{seconds} is not a time to read frames for: give a finite time above 0 s",
                                 param_hint="'--seconds'")
    hint = ""
    try:
        cfg = load_config(config)
        sensor_cfg = cfg.sensor
        if port is not None:
            if not isinstance(sensor_cfg, VL53L8CXConfig):
                raise typer.BadParameter(f"--port is for a vl53l8cx sensor, this cell has {sensor_cfg.type}")
            sensor_cfg = sensor_cfg.model_copy(update={"port": port, "i2c": None})
        if sensor_cfg.type.startswith("sim-"):
            raise JobError(f"sensor type {sensor_cfg.type} renders a simulated scene; check a hardware "
                           "(vl53l8cx, realsense) or replay sensor")
        sensor = make_sensor(sensor_cfg, None, lambda: np.eye(4))
        valid = sensor_cfg.valid_statuses if isinstance(sensor_cfg, VL53L8CXConfig) else None
        tally = SensorCheck(valid if valid is not None else VL53L8CX_VALID_STATUSES)
        failure: CellError | None = None
        # what to do when the bridge board's port does not open (the driver's error says what failed)
        board = isinstance(sensor_cfg, VL53L8CXConfig) and sensor_cfg.i2c is None \
            and "://" not in (sensor_cfg.port or "")
        hint = PORT_HINT if board else ""
        with sensor:
            hint = ""
            end = time.monotonic() + seconds
            try:
                while (frames is not None and tally.count < frames) or (
                        frames is None and time.monotonic() < end):
                    frame = sensor.capture()
                    raw = sensor.last_raw if isinstance(sensor, VL53L8CXSerial) else None
                    tally.add(frame, time.monotonic(), raw.timestamp_us if raw is not None else None)
            except CellError as exc:
                failure = exc
            link = sensor.stats if isinstance(sensor, VL53L8CXSerial) else None
            tof = isinstance(sensor_cfg, VL53L8CXConfig) or sensor.model.kind == "tof"
    except CellError as exc:
        raise fail(f"{exc}{hint}") from None
    _print_report(tally.report(), link, (valid or VL53L8CX_VALID_STATUSES) if tof else None)
    if failure is not None:
        raise fail(failure)
    if tally.count == 0:
        raise fail(DriverError(f"read no frame in {seconds:g} s: nothing to check", device=f"depth "
                                f"{sensor_cfg.type}"))


# -- emulate ---------------------------------------------------------------------------------------------

def check_command(url: str) -> str:
    """The ``cell sensor check`` that reads the emulator at ``url``: with the installed hardware template's
    sensor section (a path that exists on any PC with the cell, unlike the checkout's ``config/``)."""
    return f"cell sensor check --config {template_path('ur5e-vl53l8cx')} --port {url}"


@sensor_app.command()
def emulate(
    socket: Annotated[str | None, typer.Option(help="serve on HOST:PORT (TCP) instead of a "
                                                    "pseudo-terminal")] = None,
    object: Annotated[str, typer.Option("--object", help="shipped object the sensor sees")] = "cube",
    standoff: Annotated[float, typer.Option(help="sensor distance to the object [m]")] = 0.3,
    seed: Annotated[int, typer.Option(help="seed of the sensor noise and of the faults")] = 0,
    garbage: Annotated[int, typer.Option(help="random bytes sent before the banner")] = 0,
    corrupt: Annotated[str, typer.Option(help="ranging frame indices to corrupt, e.g. 3,7")] = "",
    corrupt_every: Annotated[int, typer.Option(help="also corrupt every N-th ranging frame")] = 0,
    drop: Annotated[str, typer.Option(help="ranging frame indices never sent (sequence gaps)")] = "",
    split: Annotated[bool, typer.Option(help="write frames in small chunks (split reads)")] = False,
    disconnect_after: Annotated[int | None, typer.Option(help="close the link after N ranging "
                                                               "frames")] = None,
) -> None:
    """Serve the VL53L8CX bridge protocol with simulated frames until Ctrl-C."""
    faults = EmulatorFaults(garbage_bytes=garbage, corrupt_frames=_int_set(corrupt),
                            corrupt_every=corrupt_every, drop_frames=_int_set(drop), split=split,
                            disconnect_after=disconnect_after)
    try:
        source = SimToFSource.fixed(object, standoff_m=standoff, seed=seed)
        if socket is not None:
            host, _, port_text = socket.rpartition(":")
            if not port_text.isdigit():
                raise typer.BadParameter(f"expected HOST:PORT, got {socket!r}")
            emulator = VL53L8CXEmulator.on_tcp(source, faults, seed, host=host or "127.0.0.1",
                                               port=int(port_text))
        else:
            emulator = VL53L8CXEmulator.on_pty(source, faults, seed)
    except (CellError, OSError) as exc:
        raise fail(exc) from None
    console.print(f"VL53L8CX bridge emulator on {emulator.url}", markup=False)
    console.print(f"  try: {check_command(emulator.url)}", markup=False)
    try:
        emulator.run()
    except KeyboardInterrupt:
        emulator.close()
    c = emulator.counters
    console.print(f"sent {c.sent} ranging frames ({c.corrupted} corrupted, {c.dropped} dropped, "
                  f"{c.overflowed} lost to a slow reader)", markup=False)


# -- replay ----------------------------------------------------------------------------------------------
class Replayed(NamedTuple):
    """What :func:`replay_perception` rebuilt: the accumulated ``cloud`` (N, 3) [m, base frame], the number
    of frames played, and the frame files it skipped as unreadable (file, reason)."""

    cloud: np.ndarray
    n_frames: int
    unreadable: list[tuple[Path, str]]


def replay_perception(job_dir: Path, cfg: CellConfig, seed: int) -> Replayed:
    """Play a job folder through the replay sensor and arm on a simulated clock into a fresh perception
    pipeline of ``cfg``; returns the accumulated cloud, the number of frames and the frames skipped as
    unreadable (:class:`Replayed`).

    Each frame's pose is read from the replay arm at the frame's time and composed with ``cfg``'s mount,
    as a live job does; perception's generator is the job's (``job_generators(seed).perception``), so
    the same cell file and seed rebuild the recorded cloud exactly.
    """
    recording = JobRecording(job_dir)
    clock = SimClock()
    arm = ReplayArm(recording, get_robot_model(cfg.arm.model), clock)
    range_m = getattr(cfg.sensor, "range_min_m", 0.02), getattr(cfg.sensor, "range_max_m", 4.0)
    sensor = ReplaySensor(recording, clock, range_m)
    perception = PerceptionPipeline(cfg.perception, table_z_m=cfg.station.table_z_m,
                                    range_max_m=sensor.model.range_max_m,
                                    rng=job_generators(seed).perception)
    T_flange_sensor = cfg.mount.matrix()
    n = 0
    with arm, sensor:
        while sensor.remaining:
            frame = sensor.capture()
            perception.process(frame, arm.state().T_base_flange @ T_flange_sensor)
            n += 1
    return Replayed(perception.cloud.points, n, recording.unreadable)


@sensor_app.command()
def replay(
    job_dir: Annotated[Path, typer.Argument(metavar="JOB_DIR", help="the recorded job's folder")],
    config: Annotated[Path | None, typer.Option(help="cell file (default: the one the job names)")] = None,
    seed: Annotated[int | None, typer.Option(help="perception seed (default: the job's)")] = None,
    out: Annotated[Path | None, typer.Option(help="folder to write cloud_replay.ply to, made if missing "
                                                  "(default: the job folder)")] = None,
) -> None:
    """Re-run a recorded job's frames and poses through perception; writes cloud_replay.ply.

    A frame that cannot be read is skipped with a warning; a result.json that is missing or unreadable
    is replaced by the job's identity in job.json (nothing is written to the job folder but
    cloud_replay.ply). A read-only job folder is refused before any work: give --out."""
    try:
        check_job_dir(job_dir)  # before output_folder, which would make it
        path = output_folder(job_dir, out, (REPLAY_CLOUD,)) / REPLAY_CLOUD
        cfg, job_result, _ = recorded_job(job_dir, config)
        if job_result.problem is not None:
            print_warning(f"{job_dir / 'result.json'} is {job_result.problem}: replaying with the job's "
                          "identity from job.json")
        result = job_result.result
        cloud, n, unreadable = replay_perception(job_dir, cfg,
                                                 seed if seed is not None else int(result.get("seed", 0)))
    except CellError as exc:
        raise fail(exc) from None
    for file, reason in unreadable:
        print_warning(f"skipped {file}: not a readable frame ({reason})")
    write_ply(path, cloud)
    skipped = f" ({len(unreadable)} unreadable frames skipped)" if unreadable else ""
    console.print(f"{n} frames replayed{skipped}, {cloud.shape[0]} points; wrote {path}", markup=False)
    recorded_path = job_dir / "cloud.ply"
    if recorded_path.is_file():
        recorded = read_ply(recorded_path)
        if recorded.shape == cloud.shape and np.array_equal(recorded, cloud):
            console.print("identical to the recorded cloud.ply", markup=False)
        elif recorded.shape[0] and cloud.shape[0]:
            d, _ = cKDTree(recorded).query(cloud)
            console.print(f"differs from cloud.ply ({recorded.shape[0]} points): nearest recorded point "
                          f"within {np.max(d) * 1e3:.3f} mm (max), {np.median(d) * 1e3:.3f} mm (median)",
                          markup=False)
