"""``cell calibrate``: the cell measures its own mount, table and ToF zones (the ``calibration`` package).

Every move goes through a job (``cell.jobs``, so the safety layer); the views' job folder, with the raw
frames and the flange poses, is kept under ``<data dir>/calibrations/<date-time>-<kind>-<target>``.
"""

from __future__ import annotations

import json
from datetime import date
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console

from calibration import guide_path
from calibration.cell_file import update_cell_file
from calibration.compare import compare_results, read_result
from calibration.mount import BOARD_TARGET, calibrate_mount, default_folder, default_poses, result_json
from calibration.table import calibrate_table, table_report
from calibration.targets import BOX_TARGETS, DEFAULT_BOX
from calibration.tof import DEFAULT_FRAMES_PER_HEIGHT, DEFAULT_HEIGHTS_M, calibrate_zones, zone_record
from cell.cli.commands import command_group
from cell.cli.errors import fail
from cell.cli.signals import interrupting
from cell.cli.values import data_folder
from cell.config import load_config
from cell.config.placeholders import require_arm_measured
from cell.service.startup import DEFAULT_DATA_DIR
from drivers.depth.zone_correction import write_zone_correction
from drivers.errors import CellError, ConfigError
from drivers.sim.board import printable_board

calibrate_app = command_group(help="Calibrate the cell with the cell: the sensor mount, the table, the ToF "
                                   "zones.", no_args_is_help=True)
console = Console(soft_wrap=True)

ConfigOption = Annotated[Path, typer.Option(help="the cell file")]
DataDirOption = Annotated[Path, typer.Option(help="the data folder; the views are kept in its calibrations/",
                                             callback=data_folder)]


def _print(text: str) -> None:
    console.print(text, markup=False, highlight=False)


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")


def _axes(values: list[float], unit: str) -> str:
    return ", ".join(f"{name} {v:.3f}" for name, v in zip("xyz", values, strict=True)) + f" {unit}"


@calibrate_app.command()
def mount(
    config: ConfigOption,
    out: Annotated[Path, typer.Option(help="where to write the result (JSON)")],
    target: Annotated[str, typer.Option(help=f"{BOARD_TARGET!r}: the cell's ChArUco board (RGB-D cameras); "
                                             f"or a known shape on the table: {', '.join(BOX_TARGETS)}")]
    = DEFAULT_BOX,
    poses: Annotated[int | None, typer.Option(min=4, help="views to plan (default: 40 for a ToF sensor, "
                                                          "30 for a camera)")] = None,
    standoff: Annotated[float | None, typer.Option(help="sensor distance to the target [m] (default: "
                                                        "scan.standoff_m)")] = None,
    write: Annotated[bool, typer.Option(help="put the mount into the cell file (comments kept), after "
                                             "showing the change")] = False,
    data_dir: DataDirOption = DEFAULT_DATA_DIR,
    seed: Annotated[int, typer.Option(help="seed of the job (simulated devices, point sampling)")] = 0,
) -> None:
    """Solve the sensor mount (hand-eye, T_flange_sensor).

    From views of the ChArUco board or of a known shape (the table and a box at the station) that the arm
    visits through the safety layer; prints it with its residual and per-axis standard deviations and
    writes the JSON result."""
    try:
        cfg = load_config(config)
        require_arm_measured(config, cfg.mode)
        folder = default_folder(data_dir, "mount", target)
        n_poses = poses if poses is not None else default_poses(cfg)
        with interrupting():
            cal = calibrate_mount(cfg, str(config), target=target, n_poses=n_poses, folder=folder, seed=seed,
                                  standoff_m=standoff)
        result = result_json(cal, str(config))
        _write_json(out, result)
        _write_json(folder / "calibration.json", result)
    except CellError as exc:
        raise fail(exc) from None
    m = result["mount"]
    _print(f"mount: xyz_m {m['xyz_m']}, rpy_deg {m['rpy_deg']} (changed by {result['change_mm']:.2f} mm, "
           f"{result['change_deg']:.3f} deg)")
    _print(f"residual {result['residual_mm']:.3f} mm RMS over {result['n_points']} points of "
           f"{result['n_views']} views ({result['n_planned']} planned, {result['n_unreachable_views']} "
           "out of "
           f"reach, refused {result['refused_moves'] or 'none'})")
    _print(f"std: {_axes(result['std_mm'], 'mm')}; about {_axes(result['std_deg'], 'deg')}")
    _print(f"wrote {out}; views kept in {folder}")
    if write:
        try:
            update_cell_file(config, {("mount", "xyz_m"): m["xyz_m"], ("mount", "rpy_deg"): m["rpy_deg"]},
                             f"calibrated by cell calibrate mount, {date.today().isoformat()}", _print)
        except CellError as exc:
            raise fail(exc) from None
        _print(f"wrote the mount into {config}")


@calibrate_app.command()
def board(
    config: ConfigOption,
    out: Annotated[Path, typer.Option(help="the image to write (PNG)")],
    dpi: Annotated[float, typer.Option(min=50.0, help="about this many pixels per inch")] = 300.0,
    margin: Annotated[float, typer.Option(min=0.0, help="white margin around the board [m]")] = 0.01,
) -> None:
    """Write the cell's ChArUco board (``calibration.board``) as an image to print.

    Printed at 100 % scale (not fitted to the page), a square is ``square_m`` wide: the PNG holds the
    resolution that makes it so. Measure a square and a marker on the print and write them into the cell
    file (``square_m``, ``marker_m``), as a printer scales a little."""
    from PIL import Image

    try:
        cfg = load_config(config)
        if cfg.calibration.board is None:
            raise ConfigError("the cell file has no calibration.board (squares, square_m, marker_m, "
                              "dictionary)", file=str(config))
        spec = cfg.calibration.board
        printable = printable_board(spec, dpi, margin)
    except CellError as exc:
        raise fail(exc) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(printable.image).save(out, format="PNG", dpi=(printable.dpi, printable.dpi))
    width, height = (1000.0 * v for v in printable.size_m)
    _print(f"wrote {out}: {spec.squares[0]} x {spec.squares[1]} squares of {1000.0 * spec.square_m:g} mm, "
           f"markers of {1000.0 * spec.marker_m:g} mm ({spec.dictionary}); {printable.image.shape[1]} x "
           f"{printable.image.shape[0]} px at {printable.dpi:.2f} dpi, {width:.0f} x {height:.0f} mm with "
           "the margin")
    _print("print it at 100 % (no fit to page), lay it flat face up on the table at the station, measure a "
           "square and a marker, and write them into calibration.board (square_m, marker_m)")


def _heights(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected heights in metres separated by commas, got {text!r}") from None
    if len(set(values)) < 2 or min(values) <= 0.0:
        raise typer.BadParameter(f"expected two or more different positive heights, got {text!r}")
    return values


@calibrate_app.command()
def tof(
    config: ConfigOption,
    out: Annotated[Path, typer.Option(help="where to write the per-zone correction (JSON)")],
    heights: Annotated[str, typer.Option(help="sensor heights above the table [m], comma-separated")]
    = ",".join(f"{h:g}" for h in DEFAULT_HEIGHTS_M),
    frames: Annotated[int, typer.Option(min=2, help="frames at each height")] = DEFAULT_FRAMES_PER_HEIGHT,
    write: Annotated[bool, typer.Option(help="set sensor.zone_correction in the cell file to --out")] = False,
    data_dir: DataDirOption = DEFAULT_DATA_DIR,
    seed: Annotated[int, typer.Option(help="seed of the job (simulated devices)")] = 0,
) -> None:
    """Measure each ToF zone's range bias and noise.

    With the sensor looking straight down at the flat, clear table beside the station from several
    heights; prints the mean absolute range error over the zones before and after the per-zone correction,
    on frames held back from the fit, and writes the correction the sensor applies
    (``sensor.zone_correction``) only when it reduces that error (else exits 1)."""
    try:
        cfg = load_config(config)
        require_arm_measured(config, cfg.mode)
        folder = default_folder(data_dir, "tof", "table")
        with interrupting():
            fit = calibrate_zones(cfg, str(config), folder=folder, heights_m=_heights(heights),
                                  frames_per_height=frames, seed=seed)
        record = zone_record(fit, str(config), folder)
        write_zone_correction(fit.correction, folder / "zone_correction.json", **record)
    except CellError as exc:
        raise fail(exc) from None
    bias_mm, noise_mm = np.abs(fit.correction.offset_m) * 1e3, fit.correction.noise_m * 1e3
    _print(f"zone bias: {bias_mm.mean():.2f} mm mean absolute, {bias_mm.max():.2f} mm at most; zone noise "
           f"{noise_mm.mean():.2f} mm mean (one standard deviation)")
    _print(f"mean absolute range error over the zones: {record['error_before_mm']:.2f} mm before, "
           f"{record['error_after_mm']:.2f} mm after ({fit.n_frames} frames; held-back half)")
    # a correction that does not reduce the error on frames it was not fitted to fits noise, not bias:
    # applying it makes every frame worse, so it is kept for the record only, not offered to the cell
    if not fit.error_after_m < fit.error_before_m:
        raise fail(f"the correction does not reduce the held-back range error: not written to {out} nor to "
                   f"the cell file (the zones' biases are within their noise, or the table is not flat and "
                   f"clear; kept for the record in {folder})")
    write_zone_correction(fit.correction, out, **record)
    _print(f"wrote {out}; views kept in {folder}")
    if write:
        try:
            update_cell_file(config, {("sensor", "zone_correction"): str(out.resolve())},
                             f"calibrated by cell calibrate tof, {date.today().isoformat()}", _print)
        except CellError as exc:
            raise fail(exc) from None
        _print(f"set sensor.zone_correction in {config}")


@calibrate_app.command()
def table(
    config: ConfigOption,
    out: Annotated[Path | None, typer.Option(help="also write the report (JSON) here")] = None,
    ring: Annotated[int, typer.Option(min=0, help="views around the station besides the one above it")] = 4,
    object: Annotated[str, typer.Option("--object", help="sim and dry runs: what stands on the station "
                                                         "(a shipped mesh; 'none': nothing)")] = "none",
    data_dir: DataDirOption = DEFAULT_DATA_DIR,
    seed: Annotated[int, typer.Option(help="seed of the job (simulated devices)")] = 0,
) -> None:
    """Find the table plane (height and tilt) and the station.

    From a short scan (the station with a part on its mark), reported against the cell file's
    ``station``."""
    try:
        cfg = load_config(config)
        require_arm_measured(config, cfg.mode)
        folder = default_folder(data_dir, "table", object)
        with interrupting():
            found = calibrate_table(cfg, str(config), folder=folder, ring=ring, target_object=object,
                                    seed=seed)
        report = table_report(found, cfg)
        _write_json(folder / "table.json", report)
        if out is not None:
            _write_json(out, report)
    except CellError as exc:
        raise fail(exc) from None
    _print(f"table at the station: z {report['table_z_at_station_m']:.4f} m (cell file "
           f"{report['cell_file_table_z_m']:.4f} m, {report['table_z_difference_mm']:+.2f} mm), tilt "
           f"{report['tilt_deg']:.3f} deg towards {report['tilt_direction_deg']:.0f} deg; residual "
           f"{report['residual_mm']:.2f} mm over {report['n_points']} points")
    if report["part_xy_m"] is not None:
        _print(f"part on the station at xy {report['part_xy_m']} m: {report['station_difference_mm']} mm "
               f"from the cell file's station {report['cell_file_station_xy_m']}")
    _print(f"wrote {out}; views kept in {folder}" if out is not None else f"views kept in {folder}")


@calibrate_app.command()
def compare(
    a: Annotated[Path, typer.Argument(metavar="A", help="a mount calibration result (JSON)")],
    b: Annotated[Path, typer.Argument(metavar="B", help="another one")],
) -> None:
    """How far two mount calibrations are apart (B less A).

    And whether that is within 3 combined standard deviations on every axis."""
    try:
        diff = compare_results(read_result(a), read_result(b))
    except CellError as exc:
        raise fail(exc) from None
    _print(f"translation: {_axes(diff['delta_xyz_mm'], 'mm')} ({diff['distance_mm']:.3f} mm)")
    _print(f"rotation: roll-pitch-yaw {diff['delta_rpy_deg']} deg ({diff['angle_deg']:.4f} deg)")
    if diff["consistent"] is not None:
        _print("consistent within their uncertainties" if diff["consistent"]
               else "NOT consistent: the mount moved, or one calibration is off")


@calibrate_app.command()
def guide() -> None:
    """Print the calibration guide: how to measure the mount, the table and the ToF zones."""
    console.print(guide_path().read_text(), markup=False, highlight=False)
