"""The segmented object on a table of known height (LR-NBV paper, section 3.2: DBSCAN on occupied voxels).

The perception pipeline finds the table with RANSAC. With a sparse 8x8 sensor the table is hit by few
rays while a wide flat object's top fills many voxels, so RANSAC can take the object's top for the table
and then leave no object at all (seen on ``horizontal_box`` with the raster planner). The cell's table
height is known (``station.table_z_m``), so the packing result and the LR-NBV planners cut the occupied
voxels at that height instead and keep the largest cluster of the configured method (DBSCAN for the ToF
cell), with the same parameters as perception.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.perception.pipeline import PerceptionPipeline
from cell.perception.segmentation import SegmentationParams, dbscan_largest_cluster, largest_euclidean_cluster

Array = NDArray[np.float64]


def segment_on_table(occupied_base: Array, params: SegmentationParams, table_z: float) -> Array:
    """The object's points (M, 3) [m, base frame]: the largest cluster (``params.method``) of the occupied
    voxel centres more than ``params.plane_distance_m`` above ``table_z`` [m]; (0, 3) when none."""
    above = occupied_base[occupied_base[:, 2] > table_z + params.plane_distance_m]
    if params.method == "euclidean":
        return largest_euclidean_cluster(above, params.cluster_tolerance_m, params.min_cluster_points)
    return dbscan_largest_cluster(above, params.dbscan_eps_m, params.dbscan_min_points,
                                  params.min_cluster_points)


def current_object(perception: PerceptionPipeline) -> Array:
    """The object in the pipeline's occupancy map now, cut at the pipeline's table height."""
    return segment_on_table(perception.map.occupied_centers(), perception.config.segmentation,
                            perception.table_z_m)
