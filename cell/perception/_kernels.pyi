"""Type stub of the compiled perception kernels (``_kernels.pyx``): the signatures mypy checks callers
against. Arrays are C-contiguous; the ``*_out`` / ``out`` arguments are filled in place. A C ``float``
parameter takes whatever ``float()`` takes (the occupancy map passes its float32 log-odds)."""

from typing import SupportsFloat, TypeAlias

import numpy as np
from numpy.typing import NDArray

F64: TypeAlias = NDArray[np.float64]
I64: TypeAlias = NDArray[np.int64]

RAY_HIT: int
RAY_FREE: int
RAY_TRUNCATED: int

def integrate_rays(origin: F64, ends: F64, resolution: float, kinds: NDArray[np.uint8],
                   index: NDArray[np.int32], ox: int, oy: int, oz: int, pool: NDArray[np.float32],
                   stamp: NDArray[np.uint32], counts: NDArray[np.uint32], sides: NDArray[np.float32],
                   n_occupied: NDArray[np.int32],
                   block_coords: I64, n_blocks: int,
                   scan: int, l_hit: SupportsFloat, l_miss: SupportsFloat, l_min: SupportsFloat,
                   l_max: SupportsFloat, l_occ: SupportsFloat, keep_surface: bool,
                   max_dense_voxels: int, lanes: bool) -> tuple[int, bool]: ...
def ray_lanes() -> bool: ...
def knn_mean_distances(points: F64, cells: I64, starts: I64, nx: int, ny: int, nz: int, cell_m: float,
                       lo: F64, k: int, out: F64) -> None: ...
def nearest_within(points: F64, starts: I64, nx: int, ny: int, nz: int, cell_m: float, lo: F64, queries: F64,
                   max_m: float, out_index: I64, out_d2: F64) -> None: ...
def point_to_plane_system(points: F64, normals: F64, starts: I64, nx: int, ny: int, nz: int, cell_m: float,
                          lo: F64, source: F64, T: F64, max_m: float, max_tangential_m: float, ata_out: F64,
                          atb_out: F64) -> tuple[int, float]: ...
def k_nearest_within(points: F64, starts: I64, nx: int, ny: int, nz: int, cell_m: float, lo: F64,
                     queries: F64, radius_m: float, out_index: I64) -> None: ...
def voxel_groups(points: F64, voxel_m: float, box_lo: F64, box_hi: F64, crop: bool, keys_out: I64,
                 sums_out: F64, counts_out: I64) -> int: ...
def plane_normals(cloud: F64, neighbours: I64, out: F64) -> None: ...
def radius_plane_normals(points: F64, starts: I64, nx: int, ny: int, nz: int, cell_m: float, lo: F64,
                         queries: F64, radius_m: float, out: F64) -> None: ...
def radius_components(points: F64, cells: I64, starts: I64, nx: int, ny: int, nz: int, radius_m: float,
                      root_out: I64) -> None: ...
def plane_inlier_counts(points: F64, normals: F64, offsets: F64, max_distance_m: float, out: I64) -> None: ...
def grid_sort(points: F64, lo: F64, cell_m: float, nx: int, ny: int, nz: int, starts_out: I64, order_out: I64,
              cells_out: I64, points_out: F64) -> None: ...
def radius_counts(points: F64, cells: I64, starts: I64, nx: int, ny: int, nz: int, radius_m: float,
                  out: I64) -> None: ...
