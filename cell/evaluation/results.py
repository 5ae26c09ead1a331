"""``results.csv``: one row per scan of a grid, from its job folder's ``result.json``.

Byte-identical for the same grid whoever ran it: rows sorted by object, placement, planner and seed;
every number written with a fixed number of decimals; nothing that depends on the machine or the wall
clock (no wall times, no paths). Empty cells are figures a scan does not have (no ground truth, no
packing history, a scan that never ran).

Columns: ``object`` (its label: a shipped name, else ``name@`` a digest of the mesh,
``ScanSpec.object_label``), ``placement`` (x,y,yaw_deg), ``planner``, ``seed``, ``status`` (the job's, or
``failed`` for a scan that left no folder, refused or its worker dead twice, or for one of a grid that
re-processes whose re-process failed: its figures are then empty, never the online cloud's), ``termination``,
``limit_reached`` (``true`` when a limit of the job, its time budget, ended the planner's run before the
planner's own termination: a scan cut short, ``--max-time``; ``false``; empty where result.json does not
say, a folder of an earlier release or a scan that left none),
``scan_time_s`` (job time from the first frame, the visual-servoing paper's clock), ``path_m`` (sensor path
over the same span), ``n_captures``, ``coverage_pct``, ``chamfer_mm``, ``hausdorff_mm`` (eq. 13 on the online
cloud; on the 1 mm re-processed cloud, ``result_hires.json``, for a grid that re-processes, as the paper
measures Table I; the ground truth registered to the cloud as the paper does), ``coverage_unregistered_pct``
and ``chamfer_unregistered_mm`` (the same without registration, the ground truth where the simulated object
really is), and the packing paper's figures: ``dims_m`` (L W H), ``iou``, ``n_poses``, ``n_useless_poses`` and
``packing_coverage_pct``, with ``dims_true_m`` (L W H of the ground-truth box: the minimum-area box of the
object's mesh, in sim only), ``dims_upper_m`` (the box's upper bound from the sensor's error model, the
box the container is chosen for) and ``container`` (its name, ``none`` when none fits; empty without a
box); last ``job``, the scan's job folder under ``scans/`` (its name holds the scan's key,
``cell.evaluation.spec``; empty for a scan that left no folder): the output folder may also hold the folders
of earlier runs, scans of other code or inputs, which are not this grid's.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Sequence
from functools import cache
from pathlib import Path
from typing import Any

from cell.evaluation.spec import ScanSpec
from cell.packing.box import box_from_points
from cell.perception.hires_files import RESULT_HIRES_FILE
from drivers.errors import CellError
from drivers.sim.objects import load_object

COLUMNS = ("object", "placement", "planner", "seed", "status", "termination", "limit_reached", "scan_time_s",
           "path_m", "n_captures", "coverage_pct", "chamfer_mm", "hausdorff_mm", "coverage_unregistered_pct",
           "chamfer_unregistered_mm", "dims_m", "iou", "n_poses", "n_useless_poses", "packing_coverage_pct",
           "dims_true_m", "dims_upper_m", "container", "job")
DECIMALS = 4

Row = dict[str, str]
RowId = tuple[str, str, str, str]
"""(object, placement, planner, seed) of a row."""
Timeline = dict[str, list[float | None]]
"""Eq. 13 as a re-processed scan went on (``result_hires.json``): ``t_s`` [s from the first frame] and
``coverage_pct``, ``chamfer_mm``, ``hausdorff_mm`` of the cloud the frames up to each one make."""


def _number(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return f"{float(value):.{DECIMALS}f}"


def _flag(value: Any) -> str:
    """A true/false of result.json as results.csv writes it: ``true``, ``false``, or empty when absent."""
    return "" if value is None else str(bool(value)).lower()


def _identity(spec: ScanSpec) -> Row:
    return dict(zip(COLUMNS[:4], identity(spec), strict=True))


REPROCESS_FAILED = "reprocess_failed.txt"
"""In a re-processed job folder, why its re-process failed (written by ``cell.evaluation.task``)."""


@cache
def true_dims(obj: str, scale: float) -> tuple[float, float, float] | None:
    """L, W, H [m] of the ground-truth box of an object (a shipped name or a mesh file at ``scale``): the
    minimum-area box of its mesh standing on the table (``cell.packing.box.box_from_points``; its size does
    not depend on where the object stands or its yaw); None when the mesh cannot be loaded."""
    try:
        mesh = load_object(obj, scale)
    except CellError:
        return None
    length, width, height = (float(d) for d in box_from_points(mesh.vertices).dims)
    return length, width, height


def _dims_text(dims: Sequence[float | None] | None) -> str:
    """L W H as results.csv writes them; empty for none, or for one with an unbounded side (None)."""
    return "" if dims is None or None in dims else " ".join(_number(d) for d in dims)


def row_from_result(spec: ScanSpec, result: dict[str, Any], hires: dict[str, Any] | None = None) -> Row:
    """The row of a scan whose job folder holds ``result`` (its result.json) and, re-processed,
    ``hires`` (its result_hires.json), whose eq. 13 figures then replace the online cloud's."""
    metrics = (hires if hires is not None else result).get("metrics") or {}
    packing = result.get("packing") or {}
    dims = packing.get("dims_m")
    upper = packing.get("dims_upper_m")
    container = packing.get("container") or {}
    truth = true_dims(spec.object, spec.object_scale) if result.get("object_pose") is not None else None
    return {**_identity(spec), "status": result["status"],
            "termination": " ".join(str(result["termination"]).split()),
            "limit_reached": _flag(result.get("limit_reached")),
            "scan_time_s": _number(result.get("scan_time_s")),
            "path_m": _number(result.get("scan_path_length_m")),
            "n_captures": _number(result.get("n_captures")),
            **{k: _number(metrics.get(k)) for k in ("coverage_pct", "chamfer_mm", "hausdorff_mm",
                                                     "coverage_unregistered_pct", "chamfer_unregistered_mm")},
            "dims_m": _dims_text(dims), "dims_true_m": _dims_text(truth), "dims_upper_m": _dims_text(upper),
            "container": "" if dims is None else str(container.get("name") or "none"),
            "iou": _number(packing.get("iou")), "n_poses": _number(packing.get("n_poses")),
            "n_useless_poses": _number(packing.get("n_useless_poses")),
            "packing_coverage_pct": _number(packing.get("coverage_pct"))}


def row_from_folder(spec: ScanSpec, folder: Path) -> Row:
    """The row of a scan from its job folder: for a spec that re-processes, the figures of its
    ``result_hires.json``, and a ``failed`` row saying why when the re-process failed (no figures: the
    online cloud's are not what the grid measures); for one that does not, the online cloud's, even where
    someone re-processed the folder since."""
    result = json.loads((folder / "result.json").read_text())
    hires = folder / RESULT_HIRES_FILE
    if not spec.reprocess:
        return {**row_from_result(spec, result), "job": folder.name}
    if hires.is_file():
        return {**row_from_result(spec, result, json.loads(hires.read_text())), "job": folder.name}
    why = folder / REPROCESS_FAILED
    reason = why.read_text().strip() if why.is_file() else "no result_hires.json"
    scanned = ("" if result["status"] == "completed"
               else f"the scan {result['status']}: {result['termination']}; ")
    return {**failed_row(spec, f"{scanned}re-process failed: {reason}"), "job": folder.name}


def timeline_from_folder(folder: Path) -> Timeline | None:
    """A re-processed scan's timeline from its job folder; None when it was not re-processed or has no
    ground truth."""
    hires = folder / RESULT_HIRES_FILE
    return json.loads(hires.read_text()).get("timeline") if hires.is_file() else None


def identity(spec: ScanSpec) -> RowId:
    """The (object, placement, planner, seed) of the spec's row."""
    return spec.object_label, spec.placement_text, spec.planner, str(spec.seed)


def row_id(row: Row) -> RowId:
    """The (object, placement, planner, seed) of a row."""
    return row["object"], row["placement"], row["planner"], row["seed"]


def failed_row(spec: ScanSpec, reason: str) -> Row:
    """The row of a scan that left no job folder (refused, or its worker died twice)."""
    return {**dict.fromkeys(COLUMNS, ""), **_identity(spec), "status": "failed",
            "termination": " ".join(reason.split())}


def _order(row: Row) -> tuple[str, tuple[float, ...], str, int]:
    return (row["object"], tuple(float(v) for v in row["placement"].split(",")), row["planner"],
            int(row["seed"]))


def sorted_rows(rows: Iterable[Row]) -> list[Row]:
    """The rows in results.csv's order: object, placement, planner, seed."""
    return sorted(rows, key=_order)


def csv_text(rows: Iterable[Row]) -> str:
    """The rows as CSV text, sorted (:func:`sorted_rows`), ``\\n`` line ends."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(sorted_rows(rows))
    return buffer.getvalue()


def read_csv(path: Path) -> list[Row]:
    """The rows of a results.csv."""
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def value(row: Row, column: str) -> float | None:
    """A numeric cell as a float; None when empty."""
    text = row[column]
    return None if text == "" else float(text)
