"""The objects a sim or dry-run cell can scan: the shipped meshes and the meshes operators upload.

Uploads are kept in ``<data-dir>/objects/<name>.<ply|obj|stl>``; a name is the file's stem made safe
(lower case letters, digits, ``-`` and ``_``), never a shipped name nor ``none`` (an empty table), never a
path. A mesh is accepted as ``cell scan --object`` accepts it (``drivers.sim.objects.load_object``: z-up,
re-centred, in metres or with the scale that converts its units, as ``--object-scale``), must be of a size
the cell scans and must stand on the cell's table at the station. A scaled mesh is kept scaled, as a PLY
file in metres.
"""

from __future__ import annotations

import logging
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell.config.models import CellConfig
from cell.jobs.placement import check_placement
from drivers.errors import CellError, ServiceError
from drivers.sim.objects import EMPTY_TABLE, ObjectMesh, list_objects, load_object, shipped_names, write_mesh

log = logging.getLogger("cell.service")

MESH_SUFFIXES = (".ply", ".obj", ".stl")
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


def _extents(e: np.ndarray) -> tuple[float, float, float]:
    return round(float(e[0]), 6), round(float(e[1]), 6), round(float(e[2]), 6)


class ObjectLibrary:
    """Shipped and uploaded objects of one cell; thread-safe."""

    def __init__(self, folder: Path, config: CellConfig) -> None:
        self.folder = folder
        self._config = config
        self._lock = threading.Lock()
        self._meshes: dict[str, ObjectMesh] = {}

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
        out (and logged), not the list."""
        shipped = [ObjectEntry(i.name, "shipped", _extents(i.extents_m), i.licence) for i in list_objects()]
        uploaded = []
        for name in self._uploaded():
            try:
                uploaded.append(ObjectEntry(name, "uploaded", _extents(self.mesh(name).extents_m)))
            except (CellError, *_READER_ERRORS) as exc:
                log.warning("uploaded object %s is left out of the list: %s", name, exc)
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

    def mesh(self, name: str) -> ObjectMesh:
        """The mesh of a known object (cached)."""
        with self._lock:
            mesh = self._meshes.get(name)
        if mesh is None:
            mesh = load_object(self.source(name))
            with self._lock:
                self._meshes[name] = mesh
        return mesh

    def add(self, filename: str, data: bytes, scale: float = 1.0) -> ObjectEntry:
        """Store an uploaded mesh file, its coordinates multiplied by ``scale`` into metres, as an object
        named after the file's stem; raises ``ServiceError`` when the name or the mesh is not
        acceptable."""
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
        with self._lock:
            if name in shipped_names() or name == EMPTY_TABLE or name in self._uploaded():
                raise ServiceError(f"an object named {name!r} exists already", reason="conflict",
                                   field="file")
            self.folder.mkdir(parents=True, exist_ok=True)
            staged = self.folder / f".upload-{name}{suffix}"
            staged.write_bytes(data)
            try:
                mesh = load_object(staged, scale)
                check_placement(self._config, mesh, (0.0, 0.0, 0.0), scale, option="the upload's scale")
            except BaseException as exc:
                staged.unlink(missing_ok=True)  # whatever failed: a staged file left behind is no object
                if isinstance(exc, CellError):
                    text = str(exc).replace(str(staged), filename).replace(staged.stem, Path(filename).stem)
                    raise ServiceError(text, reason="invalid", field="file") from None
                if isinstance(exc, _READER_ERRORS):
                    raise ServiceError(f"{filename!r} cannot be read as a mesh ({type(exc).__name__})",
                                       reason="invalid", field="file") from None
                raise
            if scale == 1.0:
                staged.rename(self.folder / f"{name}{suffix}")
            else:
                staged.unlink()
                write_mesh(mesh, self.folder / f"{name}.ply")
            self._meshes[name] = mesh
        return ObjectEntry(name, "uploaded", _extents(mesh.extents_m))
