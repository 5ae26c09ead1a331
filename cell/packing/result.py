"""The ``packing`` section of ``result.json`` (LR-NBV paper, section 4.1, the four metrics):

1. bounding-box dimensions (L, W, H) [m] of the final segmented object (the occupied voxels cut at the
   known table height, their largest cluster with what stands over its footprint, the measured points
   inside them and inside the box of every ROI of the scan, :mod:`cell.packing.objects`, and those below
   the cut above the table's noise band, less those within it above the cut,
   :mod:`cell.packing.table_band`; the box: :mod:`cell.packing.box`, its faces seen
   head on at the plane their points scatter about, those seen at the outline beyond where their points
   end: :mod:`cell.packing.faces`) and, in sim, their IoU with the ground-truth box of the posed mesh;
2. the number of poses, one per capture;
3. surface coverage [%]: the share of ground-truth surface samples (eq. 13's A of the visual-servoing
   paper: faces pointing down excluded) within ``coverage_radius_m`` of an object voxel centre;
4. the number of useless poses: captures after which the reconstructed surface did not grow. The paper
   calls useless the poses that "do not increase the reconstructed surface and instead cause a decrease":
   with the occupancy map, a capture can carve occupied voxels free or split the DBSCAN cluster, so the
   measure can fall; a capture that leaves it unchanged added nothing either, so both count. The measure is
   the coverage in sim and, without ground truth, the number of object voxels.

beside the dimensions their upper bound ``dims_upper_m`` and uncertainty ``dims_uncertainty_m`` (upper bound
minus estimate) [m] from the sensor's error model (:mod:`cell.packing.uncertainty`), and the container
chosen for the upper bound (:mod:`cell.packing.containers`): a box that is too small jams the line.

The box is measured on the captures as the table correction leaves them (``table_correction``: the sensor
mount's error and the common range offset that the table seen in every capture shows,
:mod:`cell.packing.table_calibration`), accumulated afresh into a pipeline of the scan's configuration; a
planner that keeps no captures gets the scan's own cloud and map, uncorrected.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.config.models import CellConfig
from cell.packing.box import PackingBox, box_from_points, packing_iou
from cell.packing.containers import ContainerChoice, choose_container
from cell.packing.faces import faced_box
from cell.packing.objects import (
    current_object,
    extent_points,
    in_extent,
    in_object_voxels,
    object_surface_points,
    packed_object,
    table_cut_z,
)
from cell.packing.table_band import above_table, clear_of_table, off_table
from cell.packing.table_calibration import TableCorrection, corrected_perception, table_correction
from cell.packing.uncertainty import ErrorModel, Seen, Sighting, error_model, upper_dims
from cell.perception.pipeline import PerceptionPipeline
from drivers.depth.base import SensorModel
from drivers.sim.objects import ObjectMesh

Array = NDArray[np.float64]


@dataclass
class ReconstructionHistory:
    """The segmented object (occupied voxel centres, base frame [m]) after each capture, in order, and
    each capture's points with the pose they were taken from (for the box's upper bound)."""

    objects: list[Array] = field(default_factory=list)
    sightings: list[Sighting] = field(default_factory=list)

    def record(self, perception: PerceptionPipeline) -> Array:
        """Append the object in the pipeline's map now and the pipeline's last frame (call after each
        capture); return the object."""
        obj = current_object(perception)
        self.objects.append(obj)
        if perception.latest is not None:
            latest = perception.latest
            self.sightings.append(Sighting(latest.T_base_sensor, latest.points_base, latest.free_ends_base))
        return obj


@runtime_checkable
class RecordsReconstruction(Protocol):
    """A planner that keeps a :class:`ReconstructionHistory` of its captures."""

    reconstruction: ReconstructionHistory


class JobFacts(Protocol):
    """What the packing section reads from a finished job's session."""

    n_captures: int
    perception: PerceptionPipeline

    def sensor_model(self) -> SensorModel: ...


def surface_coverage_pct(ground_truth: Array, object_points: Array, radius_m: float) -> float:
    """Share [%] of ground-truth surface points (N, 3) within ``radius_m`` [m] of an object point."""
    if object_points.shape[0] == 0 or ground_truth.shape[0] == 0:
        return 0.0
    d, _ = cKDTree(object_points).query(ground_truth, k=1, distance_upper_bound=radius_m)
    return float(100.0 * np.mean(d <= radius_m))


def count_useless(measures: list[float]) -> int:
    """Poses whose reconstruction measure (one per capture, in order) is not above the one before (0
    before the first capture)."""
    previous = 0.0
    useless = 0
    for m in measures:
        if m <= previous:
            useless += 1
        previous = m
    return useless


def _box_dict(box: PackingBox) -> dict[str, Any]:
    return {"center_xy_m": np.round(box.center_xy, 6).tolist(), "yaw_rad": round(box.yaw_rad, 6),
            "z_min_m": round(box.z_min, 6)}


def section_box(section: dict[str, Any]) -> PackingBox:
    """The estimate's box of a result.json ``packing`` section: its ``box`` (as :func:`_box_dict` writes
    it) with its ``dims_m``."""
    box = section["box"]
    return PackingBox(center_xy=np.asarray(box["center_xy_m"], dtype=float),
                      dims=np.asarray(section["dims_m"], dtype=float), yaw_rad=box["yaw_rad"],
                      z_min=box["z_min_m"])


def surface_coverage_radius_m(config: CellConfig) -> float:
    """The radius [m] of the surface coverage (metric 3): ``packing.coverage_radius_m``, else the occupancy
    map's resolution."""
    return config.packing.coverage_radius_m or config.perception.occupancy.resolution_m


def packing_section(config: CellConfig, session: JobFacts | None, planner: object,
                    mesh: ObjectMesh | None, T_base_object: Array | None,
                    ground_truth: Array | None, *, no_object: bool = False) -> dict[str, Any]:
    """The ``packing`` section of result.json for a finished job.

    ``planner`` contributes the per-capture history when it keeps one (:class:`RecordsReconstruction`);
    ``mesh`` posed at ``T_base_object`` gives the ground-truth box and ``ground_truth`` (N, 3) [m] the
    surface sample, both in sim only (None otherwise, and then ``iou`` and ``coverage_pct`` are None).

    A job that ended ``no_object`` (``no_object``: segmentation found no object above the table) measures
    no box and chooses no container: what the box's table-band points alone show there (a plate thinner
    than segmentation's cut, ``cell.jobs.placement.thinnest_part_m``) would contradict the status a
    packing line reads as "no part", and its scan never explored it as an object.
    """
    pc = config.packing
    radius = surface_coverage_radius_m(config)
    objects = packed_object(session.perception) if session is not None and not no_object \
        else np.zeros((0, 3))
    history = planner.reconstruction.objects if isinstance(planner, RecordsReconstruction) else None
    section: dict[str, Any] = {
        "dims_m": None, "iou": None, "coverage_pct": None,
        "n_poses": session.n_captures if session is not None else 0,
        "n_useless_poses": None, "container": None, "box": None, "dims_upper_m": None,
        "dims_uncertainty_m": None, "table_correction": None,
    }
    if ground_truth is not None:
        section["coverage_pct"] = round(surface_coverage_pct(ground_truth, objects, radius), 3)
    if history is not None:
        if ground_truth is not None:
            measures = [surface_coverage_pct(ground_truth, o, radius) for o in history]
        else:
            measures = [float(o.shape[0]) for o in history]
        section["n_useless_poses"] = count_useless(measures)
    if session is None or objects.shape[0] == 0:
        reason = ("none: the scan ended no_object, segmentation having found no object above the table"
                  if no_object else "none fits: no object was found")
        section["container"] = {"name": None, "reason": reason}
        return section
    recorded = planner.reconstruction.sightings if isinstance(planner, RecordsReconstruction) else []
    model = error_model(config, session.sensor_model())
    correction = table_correction(session.perception, recorded, model)
    perception, sightings = session.perception, recorded
    if correction.n_table_points:  # else nothing was measured and the scan's own pipeline stands
        corrected = [correction.apply(s) for s in recorded]
        rebuilt = corrected_perception(session.perception, corrected)
        rebuilt_objects = packed_object(rebuilt)
        if rebuilt_objects.shape[0]:
            perception, sightings, objects = rebuilt, corrected, rebuilt_objects
        else:  # the corrected captures' map lost the object the scan's holds: keep the scan's
            correction = TableCorrection.none()
    captured = np.vstack([s.points for s in sightings]) if sightings else np.zeros((0, 3))
    clear = clear_of_table(perception, sightings, model)
    low = above_table(perception, sightings, clear, model)
    cloud = np.vstack([object_surface_points(perception, objects), extent_points(perception)])
    measured = np.vstack([cloud[off_table(perception, cloud, captured, clear)], captured[low]])
    seen = _seen(perception, objects, sightings, captured, low, clear, measured, config.scan.standoff_m,
                 model)
    box = faced_box(box_from_points(measured, config.station.table_z_m, trim=pc.trim_fraction), model, seen)
    upper = upper_dims(box, model, seen, pc.trim_fraction)
    section["dims_m"] = np.round(box.dims, 6).tolist()
    section["dims_upper_m"] = _finite(upper)
    section["dims_uncertainty_m"] = _finite(upper - box.dims)
    section["box"] = _box_dict(box)
    section["table_correction"] = correction.summary()
    if mesh is not None and T_base_object is not None:
        section["iou"] = round(packing_iou(box, mesh, T_base_object), 6)
    if np.all(np.isfinite(upper)):
        choice = choose_container(upper, pc.containers, pc.margin_m)
        choice = replace(choice, reason=f"{choice.reason}, for the box's upper bound")
    else:
        choice = ContainerChoice(None, False, "none: a face of the box was seen only at the edge of the "
                                              "sensor's field of view or of the perception's crop box, so it "
                                              "has no upper bound")
    section["container"] = {
        "name": choice.container.name if choice.container is not None else None,
        "inner_dims_m": list(choice.container.inner_dims_m) if choice.container is not None else None,
        "rotated": choice.rotated,
        "reason": choice.reason,
    }
    return section


def _finite(values: Array) -> list[float | None]:
    """``values`` [m] rounded to the micrometre for result.json, None where infinite (no bound)."""
    return [round(float(v), 6) if np.isfinite(v) else None for v in values]


def _seen(perception: PerceptionPipeline, objects: Array, sightings: list[Sighting], captured: Array,
          low: NDArray[np.bool_], clear: NDArray[np.bool_], measured: Array, standoff_m: float,
          model: ErrorModel) -> Seen:
    """The object's points with their views for the head-on faces and the upper bound: each capture's
    points (``captured``, all of them concatenated) in the object's voxels, in the box of every ROI or
    where ``low`` (over ``captured``: those below the table cut above the table's noise band), and
    ``clear`` of the table's band (the selection of the estimate's points), with their surface normals on
    ``model``'s zone grid, or without captures on record the estimate's own points seen from
    ``standoff_m`` (:class:`Seen`)."""
    if not sightings:
        return Seen(measured, range_m=standoff_m)
    keep = in_object_voxels(perception.map, captured, objects) | in_extent(perception, captured) | low
    keep &= clear
    if not keep.any():
        return Seen(measured, range_m=standoff_m)
    cut = table_cut_z(perception.config.segmentation, perception.table_z_m)
    return Seen.of(sightings, keep, model, loose=clear & (captured[:, 2] > cut))
