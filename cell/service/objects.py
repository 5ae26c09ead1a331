"""The objects a sim or dry-run cell can scan: the shipped meshes and the meshes operators upload.

Uploads are kept in ``<data-dir>/objects/<name>.<ply|obj|stl>``; a name is the file's stem made safe
(lower case letters, digits, ``-`` and ``_``), never a shipped name nor ``none`` (an empty table), never a
path. A mesh is accepted as ``cell scan --object`` accepts it (``drivers.sim.objects.load_object``: z-up,
re-centred, in metres or with the scale that converts its units, as ``--object-scale``), must be of a size
the cell scans and must stand on the cell's table at the station. A scaled mesh is kept scaled, as a PLY
file in metres.

The service never keeps an uploaded mesh: a 16 MB STL takes some 60 MB once read, and a second to read.
What listing the objects and checking a job's placement need of it (:class:`ObjectOutline`: its size, its
footprint's convex hull, and the points on its surface that the search views' check tests, some 12,000
numbers) is worked out once, at the upload, and kept beside the mesh as ``<name>.json``, with the mesh
file's size and modification time; an upload without one (kept from before), whose mesh changed since or
whose outline file is damaged (not JSON, or its fields missing, short or not finite) is read once more,
the first time it is asked for, and so is one whose outline file was written before the surface points
were kept, the first time a job's placement is checked. The job's worker reads the mesh itself.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from cell.config.models import CellConfig
from cell.jobs.memory import release_freed_heap
from cell.jobs.placement import VIEW_CHECK_POINTS, check_placement, view_points
from cell.service.arm_clearance import ArmClearance
from cell.service.store import JobRecord
from drivers.atomic_file import write_text_atomic
from drivers.errors import CellError, ServiceError
from drivers.sim.objects import (
    EMPTY_TABLE,
    Array,
    ObjectMesh,
    list_objects,
    load_object,
    shipped_names,
    write_mesh,
)

log = logging.getLogger("cell.service")

MESH_SUFFIXES = (".ply", ".obj", ".stl")
OUTLINE_SUFFIX = ".json"
"""The suffix of an upload's outline file, beside its mesh (``<name>.json``)."""
# The mesh reader's own failures, beside the CellError of a mesh it read but refused (Open3D's: a
# MemoryError for an absurd element count, a RuntimeError for a broken file)
_READER_ERRORS = (MemoryError, RuntimeError)
_SAFE_NAME = re.compile(r"[^a-z0-9_-]+")


@dataclass(frozen=True)
class ObjectEntry:
    """An object the cell can scan: ``name``, ``source`` (``shipped`` or ``uploaded``), the size of its
    bounding box (x, y, z) [m] and, for shipped ones, the licence."""

    name: str
    source: str
    extents_m: tuple[float, float, float]
    licence: str | None = None


@dataclass(frozen=True)
class ObjectOutline:
    """What the service keeps of an uploaded mesh (``cell.jobs.placement`` reads nothing else):
    ``vertices`` (2K, 3) [m, object frame] the corners of the upright prism over the convex hull of its
    footprint, at z = 0 and at its height: at every yaw their footprint spans what the mesh's does;
    ``surface`` (``VIEW_CHECK_POINTS``, 3) [m, object frame] the points on its surface that the search
    views' check tests (``cell.jobs.placement.view_points``), None when read from an outline file written
    before they were kept."""

    name: str
    vertices: Array
    surface: Array | None = None

    @property
    def extents_m(self) -> Array:
        """Axis-aligned bounding-box size (x, y, z) [m], the mesh's: its footprint's extreme points are
        corners of the hull, and the prism is as tall as the mesh."""
        return np.ptp(self.vertices, axis=0)

    @classmethod
    def of(cls, mesh: ObjectMesh) -> ObjectOutline:
        xy = mesh.vertices[:, :2]
        # QJ: a footprint that is a line (a flat plate standing on edge) has a hull too; the points it
        # keeps are the mesh's own
        hull = xy[ConvexHull(xy, qhull_options="QJ").vertices]
        return cls.from_footprint(mesh.name, float(mesh.extents_m[2]), hull, view_points(mesh))

    @classmethod
    def from_footprint(cls, name: str, height_m: float, footprint: Array,
                       surface: Array | None = None) -> ObjectOutline:
        """The prism over ``footprint`` (K, 2) [m], from z = 0 to ``height_m`` [m], with ``surface``."""
        low = np.column_stack([footprint, np.zeros(len(footprint))])
        high = np.column_stack([footprint, np.full(len(footprint), height_m)])
        return cls(name, np.vstack([low, high]), surface)


def _extents(e: np.ndarray) -> tuple[float, float, float]:
    return round(float(e[0]), 6), round(float(e[1]), 6), round(float(e[2]), 6)


def _stamp(path: Path) -> list[int]:
    """The mesh file's size [bytes] and modification time [ns], which its outline file names: another
    file copied in under the name has other ones."""
    stat = path.stat()
    return [stat.st_size, stat.st_mtime_ns]


def _outline_file(mesh_file: Path) -> Path:
    return mesh_file.with_suffix(OUTLINE_SUFFIX)


def _write_outline(mesh_file: Path, outline: ObjectOutline, stamp: list[int]) -> None:
    footprint = outline.vertices[:len(outline.vertices) // 2, :2]
    assert outline.surface is not None  # an outline worked out from its mesh
    # to the micrometre: a third of the digits, and a verdict that moves only at a crop box's very edge
    surface = np.round(outline.surface, 6).tolist()
    write_text_atomic(_outline_file(mesh_file), json.dumps({
        "mesh_file": {"bytes": stamp[0], "mtime_ns": stamp[1]},
        "extents_m": outline.extents_m.tolist(), "footprint_m": footprint.tolist(), "surface_m": surface}))


def _read_outline(name: str, mesh_file: Path, stamp: list[int]) -> ObjectOutline | None:
    """The outline kept beside ``mesh_file`` when it is of this mesh file and whole, else None (its mesh is
    then read again): a footprint of fewer than three points (a hull has three at least) or a surface
    other than the ``VIEW_CHECK_POINTS`` finite points it was written with (its points edited away or
    not finite on disk) is not one this module wrote, and the placement checks would have run on what
    was left."""
    try:
        data = json.loads(_outline_file(mesh_file).read_text())
        if [data["mesh_file"]["bytes"], data["mesh_file"]["mtime_ns"]] != stamp:
            return None
        extents = np.asarray(data["extents_m"], dtype=np.float64).reshape(3)
        footprint = np.asarray(data["footprint_m"], dtype=np.float64).reshape(-1, 2)
        surface = (None if "surface_m" not in data  # written before the surface was kept
                   else np.asarray(data["surface_m"], dtype=np.float64))
    except (OSError, ValueError, TypeError, KeyError):  # none, or not one this module wrote: read the mesh
        return None
    whole = len(footprint) >= 3 and np.isfinite(extents).all() and np.isfinite(footprint).all() and (
        surface is None or (surface.shape == (VIEW_CHECK_POINTS, 3) and np.isfinite(surface).all()))
    if not whole:
        return None
    # its x and y sizes are the footprint's: only the height is read of them
    return ObjectOutline.from_footprint(name, float(extents[2]), footprint, surface)


class ObjectLibrary:
    """Shipped and uploaded objects of one cell; thread-safe. An upload's placement is checked clear of
    the arm in ``arm``'s collision world, the one the service's Starts check in."""

    def __init__(self, folder: Path, config: CellConfig, arm: ArmClearance) -> None:
        self.folder = folder
        self._config = config
        self._arm = arm
        # held while a mesh is read (one at a time: each takes tens of MB) and while uploads come and go
        self._lock = threading.Lock()
        # each upload's outline (None: its file does not read as a mesh) with its mesh file's stamp
        self._outlines: dict[str, tuple[list[int], ObjectOutline | None]] = {}

    @property
    def virtual(self) -> bool:
        """Whether the cell scans virtual objects (sim and dry-run cells); a real or replayed cell scans
        what is on its table, and an object name is only a label."""
        return self._config.mode in ("sim", "dry-run")

    def _uploaded(self) -> dict[str, Path]:
        if not self.folder.is_dir():
            return {}
        # not the dotfiles: an upload's staging file (".upload-NAME.ply") is no object
        return {p.stem: p for p in sorted(self.folder.iterdir())
                if p.suffix in MESH_SUFFIXES and p.is_file() and not p.name.startswith(".")}

    def entries(self) -> list[ObjectEntry]:
        """Every object, shipped first, by name; an uploaded file that no longer reads as a mesh is left
        out (and logged once), not the list."""
        shipped = [ObjectEntry(i.name, "shipped", _extents(i.extents_m), i.licence) for i in list_objects()]
        uploaded = []
        for name, path in self._uploaded().items():
            outline = self._outline(name, path)
            if outline is not None:
                uploaded.append(ObjectEntry(name, "uploaded", _extents(outline.extents_m)))
        return shipped + uploaded

    def source(self, name: str) -> str:
        """What the job's worker loads for ``name``: the shipped name, or the uploaded file's path.
        Raises ``ServiceError`` (invalid, field ``object``) for an unknown name."""
        if name in shipped_names():
            return name
        path = self._uploaded().get(name)
        if path is None:
            known = ", ".join([*shipped_names(), *self._uploaded()])
            raise ServiceError(f"unknown object {name!r}; known: {known}", reason="invalid", field="object")
        return str(path.resolve())

    def shape(self, name: str, *, surface: bool = False) -> ObjectMesh | ObjectOutline:
        """What the placement checks read of a known object: a shipped mesh (small, cached by
        ``load_object``) or an upload's outline, with its surface points when ``surface`` (the search
        views' check: an outline file written before they were kept has the mesh read once more).
        ``ServiceError`` (invalid, field ``object``) for an unknown name or an upload that no longer reads
        as a mesh."""
        source = self.source(name)
        if name in shipped_names():
            return load_object(source)
        outline = self._outline(name, Path(source), surface=surface)
        if outline is None:
            raise ServiceError(f"uploaded object {name!r} no longer reads as a mesh (the service's log says "
                               "why): upload it again", reason="invalid", field="object")
        return outline

    def _outline(self, name: str, path: Path, *, surface: bool = False) -> ObjectOutline | None:
        """The upload's outline (with its surface points when ``surface``): remembered, read from its file,
        or else (once per mesh file) worked out from the mesh; None when the mesh does not read (logged)."""
        try:
            stamp = _stamp(path)
        except FileNotFoundError:  # deleted meanwhile
            return None
        if self._remembers(name, stamp, surface):
            return self._outlines[name][1]
        outline = _read_outline(name, path, stamp)
        if outline is None or (surface and outline.surface is None):
            with self._lock:
                if self._remembers(name, stamp, surface):  # another thread may have read it meanwhile
                    return self._outlines[name][1]
                outline = self._read_mesh(name, path, stamp)
        self._outlines[name] = (stamp, outline)
        return outline

    def _remembers(self, name: str, stamp: list[int], surface: bool) -> bool:
        """Whether the outline remembered for ``name`` is of the mesh file ``stamp`` names, and holds its
        surface points when ``surface`` (or is None: the mesh does not read)."""
        known = self._outlines.get(name)
        return known is not None and known[0] == stamp and not (
            surface and known[1] is not None and known[1].surface is None)

    def _read_mesh(self, name: str, path: Path, stamp: list[int]) -> ObjectOutline | None:
        """An upload's outline from its mesh, kept beside it; None when it does not read (logged)."""
        try:
            outline = ObjectOutline.of(load_object(path))
        except (CellError, *_READER_ERRORS) as exc:
            log.warning("uploaded object %s is left out of the list: %s", name, exc)
            return None
        finally:
            release_freed_heap()  # the mesh's memory, given back: the service keeps none
        try:
            _write_outline(path, outline, stamp)
        except OSError as exc:  # kept in memory all the same; a restart reads the mesh again
            log.warning("the outline of uploaded object %s could not be written: %s", name, exc)
        return outline

    def add(self, filename: str, data: bytes, scale: float = 1.0) -> ObjectEntry:
        """Store an uploaded mesh file, its coordinates multiplied by ``scale`` into metres, as an object
        named after the file's stem, with its outline; raises ``ServiceError`` when the name or the mesh
        is not acceptable."""
        suffix = Path(filename).suffix.lower()
        if suffix not in MESH_SUFFIXES:
            raise ServiceError(f"{filename!r} is not a mesh file (allowed: {', '.join(MESH_SUFFIXES)})",
                               reason="invalid", field="file")
        name = _SAFE_NAME.sub("_", Path(filename).stem.lower()).strip("_")[:64]
        if not name:
            raise ServiceError(f"{filename!r} gives no usable object name", reason="invalid", field="file")
        limit = self._config.service.max_upload_mb
        if len(data) > limit * 1e6:
            raise ServiceError(f"{filename!r} is {len(data) / 1e6:.1f} MB, above the cell's {limit:g} MB",
                               reason="invalid", field="file")
        try:
            with self._lock:
                return self._add(name, filename, suffix, data, scale)
        finally:
            release_freed_heap()  # the mesh read to check it: the service keeps none

    def _add(self, name: str, filename: str, suffix: str, data: bytes, scale: float) -> ObjectEntry:
        if name in shipped_names() or name == EMPTY_TABLE or name in self._uploaded():
            raise ServiceError(f"an object named {name!r} exists already", reason="conflict", field="file")
        self.folder.mkdir(parents=True, exist_ok=True)
        staged = self.folder / f".upload-{name}{suffix}"
        scaled = self.folder / f".upload-{name}.scaled.ply"
        staged.write_bytes(data)
        try:
            mesh = load_object(staged, scale)
            check_placement(self._config, mesh, (0.0, 0.0, 0.0), scale, option="the upload's scale",
                            world=self._arm.world())
            if scale != 1.0:
                write_mesh(mesh, scaled)
                staged.unlink()
                staged = scaled
            outline = ObjectOutline.of(mesh)
            del mesh
            final = self.folder / f"{name}{staged.suffix}"
            stamp = _stamp(staged)  # a rename keeps it
            # the outline before the mesh: a listing meanwhile never finds the mesh without it
            _write_outline(final, outline, stamp)
            staged.rename(final)
        except BaseException as exc:
            # whatever failed: a staged file left behind is no object
            staged.unlink(missing_ok=True)
            scaled.unlink(missing_ok=True)
            if isinstance(exc, CellError):
                text = str(exc).replace(str(staged), filename).replace(staged.stem, Path(filename).stem)
                raise ServiceError(text, reason="invalid", field="file") from None
            if isinstance(exc, _READER_ERRORS):
                raise ServiceError(f"{filename!r} cannot be read as a mesh ({type(exc).__name__})",
                                   reason="invalid", field="file") from None
            raise
        self._outlines[name] = (stamp, outline)
        return ObjectEntry(name, "uploaded", _extents(outline.extents_m))

    def _upload_path(self, name: str) -> Path:
        """The mesh file of the upload ``name``; ``ServiceError`` (not found) when there is none."""
        path = self._uploaded().get(name)
        if path is None:
            raise ServiceError(f"no uploaded object {name!r}", reason="not found")
        return path

    def remove(self, name: str, active: Callable[[], Sequence[JobRecord]]) -> None:
        """Delete the uploaded object ``name`` (its mesh, then its outline). ``ServiceError``: conflict for
        a shipped object and not found for a name of no upload, both before ``active`` (the cell's queued
        and running jobs, from the store) is called; conflict while one of those jobs scans it: its worker
        reads the file."""
        if name in shipped_names() or name == EMPTY_TABLE:
            raise ServiceError(f"{name!r} is shipped with the cell: only uploaded objects can be deleted",
                               reason="conflict")
        self._upload_path(name)
        users = [job.id for job in active() if job.object == name]
        if users:
            raise ServiceError(f"object {name!r} is the object of {len(users)} queued or running job(s) "
                               f"({', '.join(users)}): delete it once they have ended, or cancel them",
                               reason="conflict")
        with self._lock:
            path = self._upload_path(name)  # another request may have deleted it meanwhile
            path.unlink()
            _outline_file(path).unlink(missing_ok=True)
            self._outlines.pop(name, None)
        log.info("uploaded object %s deleted", name)
