"""One scan of a grid, what makes it what it is (its key), and the grid's cross product.

A scan is keyed by the SHA-256 of its inputs: the cell file's settings (:func:`settings_digest`: its
validated model as canonical JSON, so that a comment or a change of layout keeps the key and any changed
setting changes it), the content of every file the cell file names (:func:`file_references`: mesh bodies
of the tool and the obstacles, the sensor's zone correction), the content of the object's mesh file (a
shipped object's PLY or the user's file), the placement, planner, seed, time budget, the mesh scale,
whether the job is re-processed and the software: its release version and the content of every source
file of ``cell`` and ``drivers`` (:func:`software_digest`: the modules and the compiled kernels' sources,
the same on every machine), as a working copy keeps its version while its code changes. The key names
the scan's job folder, so a second run of the same grid finds the scans already done, and any change of
an input (a changed setting, a new release, an edited module or kernel) runs the scan again: a benchmark
run again after a change measures the new code, not the scans the old code left in its output folder.
Keys made before the cell file's settings were hashed (its text was) differ from these: such a grid's
scans run once more, beside the old job folders, which stay under ``scans/`` out of its results.

An object is known in results and reports by its label (:attr:`ScanSpec.object_label`): a shipped name
as it is, anything else (a mesh file, a shipped object scaled) by its name and a digest of its mesh's
content and scale, so two meshes of one file name are two objects and a user's ``bunny.stl`` is not the
paper's bunny.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import cache
from pathlib import Path
from typing import Any

import yaml

import cell
import drivers
from cell.config import load_config
from cell.jobs.inputs import check_seed, parse_pose
from cell.jobs.runner import ScanRequest, prepare_scan
from cell.planning.registry import check_planner
from drivers.errors import CellError, ConfigError, JobError
from drivers.sim.objects import EMPTY_TABLE, OBJECTS_DIR, load_object, mesh_file_scale, shipped_names

Placement = tuple[float, float, float]
"""(x [m], y [m], yaw [deg]) of the object relative to the station, as ``cell scan --object-pose``."""

KEY_LENGTH = 12
"""Hex digits of the key in a job folder's name (48 bits: no collision within any practical grid)."""
LABEL_DIGITS = 8
"""Hex digits of a mesh's digest in its label (``ScanSpec.object_label``)."""


@dataclass(frozen=True)
class ScanSpec:
    """One scan: the cell file, the object (a shipped name or a mesh file's path), its placement, the
    planner, the job seed, the time budget [s] (None: the cell file's), the mesh scale (mesh units to
    metres) and whether the job folder is re-processed after the scan as the visual-servoing paper
    measures Table I (``cell.perception.reprocess``: 1 mm, multiway registration; ``result_hires.json``)."""

    config: str
    object: str
    placement: Placement
    planner: str
    seed: int
    max_time_s: float | None = None
    object_scale: float = 1.0
    reprocess: bool = False

    @property
    def object_label(self) -> str:
        """The object's name in tables: a shipped name at scale 1 as it is, else the name (a mesh file's
        stem) followed by ``@`` and ``LABEL_DIGITS`` hex digits of :func:`object_digest`."""
        if self.object in shipped_names() and self.object_scale == 1.0:
            return self.object
        return f"{Path(self.object).stem}@{object_digest(self.object, self.object_scale)[:LABEL_DIGITS]}"

    @property
    def placement_text(self) -> str:
        """The placement as ``x,y,yaw_deg`` (``cell scan --object-pose``'s form)."""
        return ",".join(f"{v:g}" for v in self.placement)


def mesh_file(obj: str) -> Path:
    """The file holding the object's mesh: the shipped PLY for a shipped name, else the path given."""
    return OBJECTS_DIR / f"{obj}.ply" if obj in shipped_names() else Path(obj).expanduser()


SOURCE_SUFFIXES = ("py", "pyx", "h")
"""The source files :func:`code_digest` reads: modules and the compiled kernels' Cython and C sources
(not the binaries, which differ between machines' compilers)."""


def code_digest(roots: Sequence[Path]) -> str:
    """The hex SHA-256 of each source file (``SOURCE_SUFFIXES``) under the package folders ``roots``, by
    its path from its root's parent (the package's name first) and its content."""
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(p for suffix in SOURCE_SUFFIXES for p in root.rglob(f"*.{suffix}")):
            digest.update(path.relative_to(root.parent).as_posix().encode())
            digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


@cache
def software_digest() -> str:
    """The release version and :func:`code_digest` of the ``cell`` and ``drivers`` packages: the code a
    scan runs."""
    return f"{cell.__version__} {code_digest([Path(cell.__file__).parent, Path(drivers.__file__).parent])}"


@cache
def _digest(path: Path, _mtime_ns: int, _size: int, settings: bool) -> str:
    if settings:
        model = load_config(path).model_dump(mode="json")
        # cell.config makes a relative zone_correction absolute; as the file names it, the key stays the
        # same wherever the grid's cell file lies (shards mounting --out elsewhere), and the file's
        # content counts as every referenced file's does
        written = (yaml.safe_load(path.read_text()) or {}).get("sensor")
        sensor = model.get("sensor")
        if isinstance(written, dict) and "zone_correction" in written and isinstance(sensor, dict):
            sensor["zone_correction"] = written["zone_correction"]
        return hashlib.sha256(json.dumps(model, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _read_digest(path: Path, settings: bool) -> str:
    try:
        stat = path.stat()
        return _digest(path.resolve(), stat.st_mtime_ns, stat.st_size, settings)
    except OSError as exc:
        raise JobError(f"cannot read {path}: {exc}") from None


def file_digest(path: Path) -> str:
    """The hex SHA-256 of the file's content (read again when it changed); ``JobError`` when unreadable."""
    return _read_digest(path, settings=False)


def settings_digest(config: str) -> str:
    """The hex SHA-256 of the settings of the cell file at ``config``: its validated model
    (``cell.config``, every default filled in) as canonical JSON (keys sorted), read again when the file
    changed; the same for a comment or a layout edit, another for any changed setting. ``ConfigError``
    when it does not validate."""
    return _read_digest(Path(config), settings=True)


def object_digest(obj: str, scale: float) -> str:
    """The hex SHA-256 of the object's mesh file's content and its scale."""
    return hashlib.sha256(f"{file_digest(mesh_file(obj))} {scale!r}".encode()).hexdigest()


FileReference = tuple[dict[str, Any], str, Path]
"""Where a cell file names a file: the mapping of its parsed YAML, the key, the file as the cell reads it."""


def file_references(data: Any, folder: Path) -> list[FileReference]:
    """The files the parsed cell file ``data`` (in ``folder``) names, in its order: the sensor's
    ``zone_correction`` (a relative name from the cell file's folder, as ``cell.config`` takes it) and
    the ``path`` of every mesh body of ``safety.collision.tool`` and ``obstacles`` (a relative one from
    the working directory, as ``cell.safety.collision`` reads it)."""
    refs: list[FileReference] = []
    if not isinstance(data, dict):
        return refs
    sensor = data.get("sensor")
    if isinstance(sensor, dict) and isinstance(sensor.get("zone_correction"), str):
        refs.append((sensor, "zone_correction", folder / Path(sensor["zone_correction"]).expanduser()))
    safety = data.get("safety")
    collision = safety.get("collision") if isinstance(safety, dict) else None
    if isinstance(collision, dict):
        for body in [*(collision.get("tool") or []), *(collision.get("obstacles") or [])]:
            if isinstance(body, dict) and body.get("shape") == "mesh" and isinstance(body.get("path"), str):
                refs.append((body, "path", Path(body["path"]).expanduser().resolve()))
    return refs


def cell_file_references(config: str) -> list[FileReference]:
    """:func:`file_references` of the cell file at ``config``; ``ConfigError`` when it is unreadable."""
    path = Path(config)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read the cell file: {exc}", file=config) from None
    return file_references(data, path.resolve().parent)


def input_digest(config: str, object: str, **inputs: object) -> str:
    """The hex SHA-256 of the cell file's settings (:func:`settings_digest`), the contents of the files it
    names (:func:`file_references`) and of the object's mesh, the software (:func:`software_digest`) and
    ``inputs`` (JSON values)."""
    everything = {**inputs, "config": settings_digest(config),
                  "files": [file_digest(path) for _, _, path in cell_file_references(config)],
                  "object": file_digest(mesh_file(object)), "software": software_digest()}
    return hashlib.sha256(json.dumps(everything, sort_keys=True).encode()).hexdigest()


def scan_key(spec: ScanSpec) -> str:
    """The key of a scan: :func:`input_digest` of all its inputs (module docstring)."""
    return input_digest(**asdict(spec))


def folder_name(spec: ScanSpec, key: str) -> str:
    """The job folder's name: readable, then the key."""
    return f"{spec.object_label}-{spec.planner}-s{spec.seed}-{key[:KEY_LENGTH]}"


def cross(config: str, cases: Sequence[tuple[str, Placement]], planners: Sequence[str], seeds: Sequence[int],
          max_time_s: float | None = None, reprocess: bool = False,
          object_scale: float = 1.0) -> list[ScanSpec]:
    """Every case (an object at a placement) x planner x seed; ``object_scale`` applies to the mesh files
    among the objects, not to shipped objects (in metres: ``mesh_file_scale``)."""
    return [ScanSpec(config, obj, placement, planner, seed, max_time_s, mesh_file_scale(obj, object_scale),
                     reprocess)
            for obj, placement in cases for planner in planners for seed in seeds]


def check_specs(specs: Sequence[ScanSpec]) -> None:
    """Refuse a grid that cannot run before any scan does (``CellError``, one line): an empty one, an
    unknown planner, an empty table (``none``: nothing to measure), an object that is neither a shipped
    name nor a readable mesh file, and every scan that ``cell scan`` would refuse before it starts
    (``cell.jobs.runner.prepare_scan``: the seed, the time budget, the object's size at its scale and
    its placement on the table, ...); and a cell file, or a file it names, that cannot be read."""
    if not specs:
        raise CellError("the grid is empty: give objects and planners")
    for planner in dict.fromkeys(s.planner for s in specs):
        check_planner(planner)
    for obj, scale in dict.fromkeys((s.object, s.object_scale) for s in specs):
        if obj == EMPTY_TABLE:
            raise JobError(f"an evaluation measures an object: {EMPTY_TABLE!r} (an empty table) has "
                           "nothing to measure; give shipped names or mesh files")
        load_object(obj, scale)
    configs = {config: load_config(config) for config in dict.fromkeys(s.config for s in specs)}
    for config in configs:
        for _, _, path in cell_file_references(config):
            file_digest(path)
    for seed in dict.fromkeys(s.seed for s in specs):
        check_seed(seed)
    # Of prepare_scan's checks only the seed's range depends on the seed, and none on re-processing: one
    # scan of each other combination tells what all its seeds would (a grid's seeds share the rest).
    with tempfile.TemporaryDirectory(prefix="cell-eval-check-") as tmp:
        for s in dict.fromkeys(replace(s, seed=0, reprocess=False) for s in specs):
            prepare_scan(ScanRequest(config=configs[s.config], config_path=s.config, object=s.object,
                                     object_pose=s.placement, planner=s.planner, seed=s.seed,
                                     out=Path(tmp) / "job", max_time_s=s.max_time_s,
                                     object_scale=s.object_scale))


def load_placements(path: Path) -> list[Placement]:
    """A placements file: YAML, a list of ``[x_m, y_m, yaw_deg]`` (or ``"x,y,yaw_deg"`` strings)."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the placements: {exc}") from None
    if not isinstance(data, list) or not data:
        raise ConfigError(f"{path}: expected a non-empty list of [x_m, y_m, yaw_deg]")
    placements = []
    for item in data:
        if isinstance(item, str):
            try:
                placements.append(parse_pose(item))
            except JobError as exc:
                raise ConfigError(f"{path}: {exc}") from None
        elif isinstance(item, list) and len(item) == 3 and all(isinstance(v, int | float) for v in item):
            placements.append((float(item[0]), float(item[1]), float(item[2])))
        else:
            raise ConfigError(f"{path}: a placement is [x_m, y_m, yaw_deg], got {item!r}")
    return placements
