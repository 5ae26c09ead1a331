"""The segmented object on a table of known height (LR-NBV paper, section 3.2: DBSCAN on occupied voxels).

The perception pipeline finds the table with RANSAC. With a sparse 8x8 sensor the table is hit by few
rays while a wide flat object's top fills many voxels, so RANSAC can take the object's top for the table
and then leave no object at all (seen on ``horizontal_box`` with the raster planner). The cell's table
height is known (``station.table_z_m``), so the packing result and the LR-NBV planners cut the occupied
voxels at that height instead and keep the largest cluster of the configured method (DBSCAN for the ToF
cell), with the same parameters as perception.

The packing box is measured on the points the sensor returned inside those voxels
(:func:`object_surface_points`) rather than on the voxel centres: a centre is up to half a voxel
(5 mm at 1 cm) from the surface it stands for, on a staircase when the box is turned against the grid,
which grew a 10 cm box by 1-2 cm per side and turned its yaw by up to 10 deg.

The final map's cluster can also lack a piece the scan did see: rays passing a curved surface at a
grazing angle carve its one-voxel shell, and the piece split off stays out of the largest cluster
until a view hits it again (a VS-Hybrid banana scan ended 4.9 cm wide, against 6.9 cm). So the box
also takes the measured points inside the box of every ROI of the scan (:func:`extent_points`,
``cell.perception.segmentation.ObjectExtent``): the object stands still, and what its ROI once held
is still the object.

A piece can also be cut off from the cluster for the whole scan, so that no ROI ever held it: a part
too thin for the map to fill between its measured voxels (the held-out lamp's 16 mm rod, ranged only in
the few zones its width filled, its voxels more than the clustering radius above the disc it stands
on). What stands over the object's footprint travels with it, whatever holds it there, so the packing
box is measured on :func:`packed_object`: the largest cluster and every other cluster above the table
cut whose centroid lies over the largest's footprint, however small (DBSCAN has already left its noise
out; the lamp's rod was 8 voxels on one NBV scan). The planners keep the papers' largest cluster
(:func:`current_object`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from cell.perception.occupancy import OccupancyMap
from cell.perception.pipeline import PerceptionPipeline
from cell.perception.segmentation import SegmentationParams, cluster_labels, largest_cluster, largest_label

Array = NDArray[np.float64]


def table_cut_z(params: SegmentationParams, table_z: float) -> float:
    """Height [m, base frame] above which :func:`segment_on_table` takes points to be the object's:
    ``params.plane_distance_m`` above the known table height ``table_z`` [m]."""
    return table_z + params.plane_distance_m


def _above_cut(occupied_base: Array, params: SegmentationParams, table_z: float) -> Array:
    """The occupied voxel centres (N, 3) [m, base frame] above :func:`table_cut_z`."""
    return occupied_base[occupied_base[:, 2] > table_cut_z(params, table_z)]


def segment_on_table(occupied_base: Array, params: SegmentationParams, table_z: float) -> Array:
    """The object's points (M, 3) [m, base frame]: the largest cluster (``params.method``) of the occupied
    voxel centres above :func:`table_cut_z`; (0, 3) when none."""
    return largest_cluster(_above_cut(occupied_base, params, table_z), params)


def stacked_on_table(occupied_base: Array, params: SegmentationParams, table_z: float) -> Array:
    """:func:`segment_on_table`'s cluster with every other cluster (DBSCAN's noise is none) whose centroid
    lies over its footprint (the convex hull of its points on the table plane): what stands on the object
    or hangs over it (module docstring); (0, 3) when there is no object."""
    above = _above_cut(occupied_base, params, table_z)
    labels = cluster_labels(above, params)
    largest = largest_label(labels, params.min_cluster_points)
    if largest < 0:
        return np.zeros((0, 3))
    clustered = labels >= 0
    label = labels[clustered]
    counts = np.bincount(label)
    if np.count_nonzero(counts) == 1:
        return above[labels == largest]
    sums = [np.bincount(label, weights=above[clustered, a], minlength=counts.size) for a in (0, 1)]
    centroids = np.column_stack(sums) / np.maximum(counts, 1)[:, None]
    # joggled ("QJ"): a cluster one voxel thick has a flat footprint, and no centroid lies over it;
    # a x + b y + c <= 0 inside every facet
    facets = ConvexHull(above[labels == largest, :2], qhull_options="QJ").equations
    over = np.all(centroids @ facets[:, :2].T + facets[:, 2] <= 0.0, axis=1) & (counts > 0)
    over[largest] = True
    return above[clustered & over[np.maximum(labels, 0)]]


def current_object(perception: PerceptionPipeline) -> Array:
    """The object in the pipeline's occupancy map now, cut at the pipeline's table height."""
    return segment_on_table(perception.map.occupied_centers(), perception.config.segmentation,
                            perception.table_z_m)


def packed_object(perception: PerceptionPipeline) -> Array:
    """The object the packing box is measured on: :func:`current_object` with what stands over its
    footprint (:func:`stacked_on_table`)."""
    return stacked_on_table(perception.map.occupied_centers(), perception.config.segmentation,
                            perception.table_z_m)


def in_object_voxels(occupancy: OccupancyMap, points: Array, object_voxels: Array) -> NDArray[np.bool_]:
    """Mask (K,) of the ``points`` (K, 3) [m, base frame] that lie in a voxel of ``object_voxels`` (their
    centres, (M >= 1, 3)) of ``occupancy``."""
    keys = occupancy.keys_of(object_voxels)
    lo = keys.min(axis=0)
    shape = tuple(int(n) for n in keys.max(axis=0) - lo + 1)
    is_object = np.zeros(shape, dtype=bool)
    is_object[tuple((keys - lo).T)] = True
    pk = occupancy.keys_of(points) - lo
    inside = np.all((pk >= 0) & (pk < np.array(shape)), axis=1)
    mask = np.zeros(points.shape[0], dtype=bool)
    mask[inside] = is_object[tuple(pk[inside].T)]
    return mask


def object_surface_points(perception: PerceptionPipeline, object_voxels: Array) -> Array:
    """The object's measured surface (K, 3) [m, base frame]: the points of the accumulated cloud that lie
    in the voxels of ``object_voxels`` (their centres, (M >= 1, 3)), plus the centre of each such voxel
    that holds none of them (a cloud point is a voxel-filtered mean and can sit across a map voxel face)."""
    if object_voxels.shape[0] == 0:
        raise ValueError("object_surface_points: no object voxels")
    cloud = perception.cloud.points
    in_object = in_object_voxels(perception.map, cloud, object_voxels)
    held = in_object_voxels(perception.map, object_voxels, cloud[in_object]) if in_object.any() else \
        np.zeros(object_voxels.shape[0], dtype=bool)
    return np.vstack([cloud[in_object], object_voxels[~held]])


def extent_box(perception: PerceptionPipeline) -> tuple[Array, Array] | None:
    """The box (min, max) (3,) [m, base frame] of every ROI of the scan (``perception.extent``), grown by
    half a voxel from the voxel centres it was taken on to the voxels' faces; None before any ROI."""
    extent = perception.extent
    if extent.min_m is None or extent.max_m is None:
        return None
    half = perception.map.resolution_m / 2.0
    return extent.min_m - half, extent.max_m + half


def in_extent(perception: PerceptionPipeline, points: Array) -> NDArray[np.bool_]:
    """Mask (K,) of the ``points`` (K, 3) [m, base frame] inside :func:`extent_box` and above
    :func:`table_cut_z`; all False before any ROI."""
    box = extent_box(perception)
    if box is None:
        return np.zeros(points.shape[0], dtype=bool)
    lo, hi = box
    lo[2] = max(lo[2], table_cut_z(perception.config.segmentation, perception.table_z_m))
    return np.all((points > lo) & (points <= hi), axis=1)


def extent_points(perception: PerceptionPipeline) -> Array:
    """The accumulated cloud's points (K, 3) [m, base frame] in :func:`in_extent`; (0, 3) before any
    ROI."""
    cloud = perception.cloud.points
    return cloud[in_extent(perception, cloud)]
