"""``cell calibrate mount``: plan views of the target, run them through the cell, solve for the mount and
say how good it is.

Known shape (any depth sensor): the views of ``calibration.views.mount_views`` around the box at the
station; before the arm moves, the planned views are checked to observe every mount axis on points
predicted by ray casting (``calibration.predict``), then the mount is fitted to the measured points
(``calibration.shape_fit``). The job folder of the views keeps the raw frames and the flange poses, so a
later calibration can be compared with this one or re-solved from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calibration import CALIBRATIONS_FOLDER
from calibration.board_fit import BoardFit, fit_mount_to_board, load_board_views
from calibration.predict import check_views_observable
from calibration.shape_fit import Array, ShapeFit, fit_mount_to_shape
from calibration.targets import box_target
from calibration.views import capture_views, load_views, mount_views
from cell.config.models import CellConfig
from drivers.depth.base import SensorModel
from drivers.errors import CalibrationError
from drivers.sim.objects import EMPTY_TABLE
from drivers.transforms import inv_T, rotvec

METHOD_SHAPE = "known-shape"
METHOD_BOARD = "charuco"
BOARD_TARGET = "charuco"
BOARD_ELEVATION_DEG = (50.0, 85.0)
"""Board views look down more steeply than box views: the markers must stay readable."""
TOF_TYPES = ("sim-tof", "vl53l8cx")
TOF_FRAMES_PER_VIEW = 5
"""Frames a ToF sensor takes at each view: its 64 zones are noisy (about 5 mm at 0.4 m), and averaging
over frames costs no motion."""
TOF_POSES = 40
CAMERA_POSES = 30


@dataclass(frozen=True)
class MountCalibration:
    """A solved mount: the fit, the mount it started from, the views' job folder and its result (how many
    views were planned, captured, refused)."""

    fit: ShapeFit | BoardFit
    T_start: Array
    target: str
    folder: Path
    job_result: dict[str, Any]
    n_planned: int


def pose_dict(T: Array) -> dict[str, list[float]]:
    """A transform as the cell file's ``xyz_m`` [m] and extrinsic ``rpy_deg`` [deg]."""
    return {"xyz_m": np.round(T[:3, 3], 6).tolist(),
            "rpy_deg": np.round(Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True), 4).tolist()}


def pose_difference(T_a: Array, T_b: Array) -> tuple[float, float]:
    """Translation [m] and rotation angle [deg] between two transforms."""
    return (float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])),
            float(np.degrees(np.linalg.norm(rotvec(T_a[:3, :3].T @ T_b[:3, :3])))))


def default_poses(config: CellConfig) -> int:
    """How many views a mount calibration plans by default: ``TOF_POSES`` for a ToF sensor (64 noisy
    zones a frame), ``CAMERA_POSES`` for a camera."""
    return TOF_POSES if config.sensor.type in TOF_TYPES else CAMERA_POSES


def default_folder(data_dir: Path, kind: str, target: str) -> Path:
    """Where a calibration's raw views go: ``<data_dir>/calibrations/<date-time>-<kind>-<target>``."""
    return data_dir / CALIBRATIONS_FOLDER / f"{datetime.now().strftime('%Y%m%d-%H%M%S')}-{kind}-{target}"


def calibrate_mount(config: CellConfig, config_path: str, *, target: str, n_poses: int, folder: Path,
                    seed: int = 0, standoff_m: float | None = None,
                    object_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> MountCalibration:
    """Calibrate the mount against ``target`` from ``n_poses`` planned views at ``standoff_m`` [m]
    (default: the cell's ``scan.standoff_m``), starting from the cell file's ``mount``: the ChArUco board
    (``BOARD_TARGET``, the cell's ``calibration.board`` lying on the table at the station) or a known
    shape (a box of ``calibration.targets``). In sim and dry runs the box stands at ``object_pose`` (x, y,
    yaw_deg) from the station; the fit starts from the station, yaw 0, and finds where it is."""
    standoff = standoff_m if standoff_m is not None else config.scan.standoff_m
    if target == BOARD_TARGET:
        return _calibrate_with_board(config, config_path, n_poses, folder, seed, standoff)
    box = box_target(target)
    T_start = config.mount.matrix()
    views = mount_views(config, n_poses, float(box.size_m[2]), standoff)
    box0 = np.array([config.station.xy_m[0], config.station.xy_m[1], 0.0])
    table_z = config.station.table_z_m

    def precheck(model: SensorModel, sensor_poses: list[Array]) -> None:
        flange = [T @ inv_T(T_start) for T in sensor_poses]
        check_views_observable(model, flange, T_start, box, box0, table_z)

    frames = TOF_FRAMES_PER_VIEW if config.sensor.type in TOF_TYPES else 1
    outcome = capture_views(config, config_path, views, target_object=target, folder=folder, seed=seed,
                            object_pose=object_pose, precheck=precheck, frames_per_view=frames)
    fit = fit_mount_to_shape(load_views(outcome.folder), T_start, box, box0, table_z, seed=seed)
    return MountCalibration(fit=fit, T_start=T_start, target=target, folder=outcome.folder,
                            job_result=outcome.result, n_planned=len(views))


def _calibrate_with_board(config: CellConfig, config_path: str, n_poses: int, folder: Path, seed: int,
                          standoff_m: float) -> MountCalibration:
    board = config.calibration.board
    if board is None:
        raise CalibrationError("the cell file has no calibration.board (the ChArUco board's squares, their "
                               "size, the markers' size and dictionary)")
    views = mount_views(config, n_poses, 0.0, standoff_m, elevation_deg=BOARD_ELEVATION_DEG)
    outcome = capture_views(config, config_path, views, target_object=EMPTY_TABLE, folder=folder, seed=seed)
    fit = fit_mount_to_board(*load_board_views(outcome.folder, board))
    return MountCalibration(fit=fit, T_start=config.mount.matrix(), target=BOARD_TARGET,
                            folder=outcome.folder, job_result=outcome.result, n_planned=len(views))


def result_json(cal: MountCalibration, config_path: str) -> dict[str, Any]:
    """The JSON ``cell calibrate mount`` writes (see the issue's format): the mount, its residual [mm],
    the views used, the per-axis standard deviations ([mm], [deg] about the flange axes), and the
    record: method, target, start mount, change, where the box and the table were found, the views'
    folder and counts."""
    fit = cal.fit
    moved_m, moved_deg = pose_difference(cal.T_start, fit.T_flange_sensor)
    job = cal.job_result
    return {
        "mount": pose_dict(fit.T_flange_sensor),
        "residual_mm": round(fit.residual_m * 1e3, 4),
        "n_views": fit.n_views,
        "std_mm": np.round(fit.std_m * 1e3, 4).tolist(),
        "std_deg": np.round(np.degrees(fit.std_rad), 5).tolist(),
        "method": METHOD_BOARD if isinstance(fit, BoardFit) else METHOD_SHAPE,
        "target": cal.target,
        "config": config_path,
        "date": datetime.now().isoformat(timespec="seconds"),
        "start_mount": pose_dict(cal.T_start),
        "change_mm": round(moved_m * 1e3, 4),
        "change_deg": round(moved_deg, 5),
        "n_points": fit.n_points,
        **fit.record(),
        "views_dir": str(cal.folder),
        "n_planned": cal.n_planned,
        "n_captured": job.get("n_captures"),
        "n_unreachable_views": job.get("n_unreachable_views"),
        "refused_moves": job.get("refused_moves"),
    }
