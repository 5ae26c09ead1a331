"""Where an object may be put: on the simulated table, whole.

Sim and dry-run jobs place a virtual object at (x [m], y [m], yaw [deg]) relative to the station; its
footprint (the mesh's vertices turned by the yaw, projected on the table) must lie on the table of the
cell's ``sim`` section, or the object would float beside it and the scan would report nonsense.
"""

from __future__ import annotations

import numpy as np

from cell.config.models import CellConfig
from drivers.errors import JobError
from drivers.sim.objects import ObjectMesh


def footprint_bounds(config: CellConfig, mesh: ObjectMesh,
                     pose: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) (2,) [m] of the object's footprint in the base frame at ``pose`` from the station."""
    x, y, yaw_deg = pose
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    xy = mesh.vertices[:, :2] @ np.array([[c, s], [-s, c]]) + np.asarray(config.station.xy_m) + (x, y)
    return xy.min(axis=0), xy.max(axis=0)


def check_on_table(config: CellConfig, mesh: ObjectMesh, pose: tuple[float, float, float]) -> None:
    """Raise ``JobError`` naming the table's extent when the object's footprint at ``pose`` leaves it."""
    lo, hi = footprint_bounds(config, mesh, pose)
    centre, size = np.asarray(config.sim.table_center_xy_m), np.asarray(config.sim.table_size_m)
    t_lo, t_hi = centre - size / 2.0, centre + size / 2.0
    if np.all(lo >= t_lo - 1e-9) and np.all(hi <= t_hi + 1e-9):
        return
    raise JobError(f"object pose {list(pose)} puts {mesh.name} off the table: its footprint spans "
                   f"x {lo[0]:.3f}..{hi[0]:.3f} m, y {lo[1]:.3f}..{hi[1]:.3f} m (base frame); the table "
                   f"spans x {t_lo[0]:.3f}..{t_hi[0]:.3f} m, y {t_lo[1]:.3f}..{t_hi[1]:.3f} m")
