"""One scan as a task of an executor: what a worker gets, what it runs, what it sends back.

A worker may be another machine (a Ray cluster) without the driver's files, so the task carries the cell
file's text, the bytes of every file the cell file names (``cell.evaluation.spec.file_references``: mesh
bodies, a zone correction) and a user mesh's bytes; the worker writes them to a private temporary folder
(the cell file's copy naming the copies of its files), runs the scan
there (``cell.jobs.runner.run_scan``, then ``cell.perception.reprocess`` when the spec asks) and sends
the whole job folder back as an in-memory tar archive, which the driver unpacks under ``--out``. The job
records the driver's cell-file path and the driver's absolute path of a user mesh, not the worker's
temporary copies: ``cell scan --replay`` and ``cell reprocess`` of the folder on the driver find the
ground truth.
"""

from __future__ import annotations

import io
import json
import tarfile
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import yaml

from cell.config import load_config
from cell.evaluation.results import REPROCESS_FAILED
from cell.evaluation.spec import ScanSpec, cell_file_references, file_references, mesh_file
from cell.jobs.runner import ScanRequest, run_scan
from cell.perception.reprocess import reprocess_job
from drivers.errors import CellError
from drivers.sim.objects import shipped_names

JOB_DIR = "job"


@dataclass(frozen=True)
class ScanTask:
    """A scan to run: its spec, key, the cell file's text, the bytes of the files it names (in
    ``file_references``' order) and, for a user mesh, the file's bytes."""

    spec: ScanSpec
    key: str
    config_text: str
    mesh_bytes: bytes | None
    config_files: tuple[bytes, ...] = ()
    mesh_origin: str | None = None
    """The user mesh's absolute path on the driver: what the job folder records as its object."""

    @classmethod
    def of(cls, spec: ScanSpec, key: str) -> ScanTask:
        user_mesh = spec.object not in shipped_names()
        mesh = mesh_file(spec.object).read_bytes() if user_mesh else None
        files = tuple(path.read_bytes() for _, _, path in cell_file_references(spec.config))
        origin = str(mesh_file(spec.object).resolve()) if user_mesh else None
        return cls(spec, key, Path(spec.config).read_text(), mesh, files, origin)

    @contextmanager
    def materialised(self) -> Iterator[tuple[Path, Path, str]]:
        """A private temporary folder holding the cell file's copy (:meth:`write_config`) and the user
        mesh's: (the folder, the cell file's copy, the object to load), removed after."""
        with tempfile.TemporaryDirectory(prefix="cell-eval-") as tmp:
            root = Path(tmp)
            obj = self.spec.object
            if self.mesh_bytes is not None:
                mesh_path = root / "mesh" / Path(obj).name
                mesh_path.parent.mkdir()
                mesh_path.write_bytes(self.mesh_bytes)
                obj = str(mesh_path)
            yield root, self.write_config(root), obj

    def write_config(self, root: Path) -> Path:
        """The cell file's copy in ``root``, and copies of the files it names under ``root/files``, which
        the copy names instead (the text as it came when it names none)."""
        path = root / Path(self.spec.config).name
        data = yaml.safe_load(self.config_text)
        refs = file_references(data, root)
        if not refs:
            path.write_text(self.config_text)
            return path
        (root / "files").mkdir()
        for n, ((holder, key, original), content) in enumerate(zip(refs, self.config_files, strict=True)):
            copy = root / "files" / f"{n}-{original.name}"
            copy.write_bytes(content)
            holder[key] = str(copy)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path


@dataclass(frozen=True)
class TaskOutput:
    """What a worker sends back: the key, the job folder as tar bytes (None when the scan was refused
    before its folder existed) and the one-line reason of a refusal or failure (None when it ran)."""

    key: str
    archive: bytes | None
    error: str | None


def pack_folder(folder: Path) -> bytes:
    """``folder``'s files as an uncompressed tar archive in memory, paths relative to it."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(folder, arcname=".")
    return buffer.getvalue()


def unpack_folder(archive: bytes, folder: Path) -> None:
    """Extract a :func:`pack_folder` archive into ``folder`` (created); refuses paths leaving it."""
    folder.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r") as tar:
        tar.extractall(folder, filter="data")


RECORDS = ("result.json", "job.json")
"""The files of a job folder that name its object (``cell.jobs.recorder``)."""


def record_object(folder: Path, obj: str) -> None:
    """Name ``obj`` as the object of the job in ``folder`` (in place of the worker's temporary copy of
    its mesh), where replay and re-process read it (the ground truth of their metrics)."""
    for name in RECORDS:
        path = folder / name
        if path.is_file():
            record = json.loads(path.read_text())
            record["object"] = obj
            path.write_text(json.dumps(record, indent=2, allow_nan=True) + "\n")


def run_scan_task(task: ScanTask) -> TaskOutput:
    """Run the task's scan in a temporary folder and return its job folder (never raises for a scan's
    failure: a failed job's folder holds its result and the reason comes back with it). The folder names
    the driver's mesh file as its object, not the worker's copy (``record_object``)."""
    spec = task.spec
    with task.materialised() as (root, config_path, obj):
        folder = root / JOB_DIR
        error = None
        try:
            config = load_config(config_path)
            run_scan(ScanRequest(config=config, config_path=spec.config, object=obj,
                                 object_pose=spec.placement, planner=spec.planner, seed=spec.seed,
                                 out=folder, max_time_s=spec.max_time_s, object_scale=spec.object_scale))
            if spec.reprocess:
                # the crop box from the task's copy: the job names the driver's file, absent on a cluster
                try:
                    reprocess_job(folder, crop=config.perception.crop_box)
                except CellError as exc:
                    (folder / REPROCESS_FAILED).write_text(f"{type(exc).__name__}: {exc}\n")
                    raise
        except CellError as exc:
            error = f"{type(exc).__name__}: {exc}"
        except Exception as exc:
            error = f"internal error: {type(exc).__name__}: {exc}"
        if task.mesh_origin is not None:
            record_object(folder, task.mesh_origin)
        archive = pack_folder(folder) if (folder / "result.json").is_file() else None
    return TaskOutput(task.key, archive, error)
