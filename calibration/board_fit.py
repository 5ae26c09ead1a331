"""Hand-eye calibration of a camera with a ChArUco board (OpenCV's aruco module), for RGB-D cameras.

Per view: the board's corners are detected in the grey image (``cv2.aruco.CharucoDetector``); a view
with fewer than ``MIN_CORNERS`` is skipped and counted, not an error. The board's pose in the camera
comes from ``cv2.solvePnP`` with the frame's intrinsics (the grey image is registered to the depth
image; no lens distortion is modelled). OpenCV's ``calibrateHandEye`` then solves the mount from the
flange poses and those board poses with Tsai's, Park's and Daniilidis' methods on all views but every
``HOLD_BACK``-th; each method's mount, with the board's pose in the base frame it implies (the mean over
the training views), is scored by the RMS reprojection error of the held-back views' corners, and the
best one is kept. Last, the mount and the board's pose are refined together by least squares of the
reprojection error of every corner of every view (pixels), whose Jacobian gives the per-axis standard
deviations and the observability test (``calibration.shape_fit.check_observable``, in pixels).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.shape_fit import N_MOUNT, Array, mount_from_params, mount_std
from drivers.errors import CalibrationError
from drivers.sim.board import BoardConfig, import_cv2
from drivers.transforms import inv_T, make_T, transform_points

MIN_CORNERS = 6
MIN_VIEWS = 5
HOLD_BACK = 4
HAND_EYE_METHODS = ("tsai", "park", "daniilidis")


@dataclass(frozen=True)
class BoardView:
    """One view of the board: the reported flange pose (4x4, base frame), the corners' board-frame
    coordinates (N, 3) [m] and their pixels (N, 2), and the camera's intrinsics K (3, 3) [px]."""

    T_base_flange: Array
    object_points: Array
    image_points: Array
    K: Array


@dataclass(frozen=True)
class BoardFit:
    """The fitted mount (4x4), the RMS reprojection error [px] and its equivalent at the board [m], the
    per-axis standard deviations (translation [m], rotation [rad], flange axes), the board's pose in the
    base frame, the held-back RMS error of each hand-eye method [px] and the one kept, and the views and
    corners used and the views skipped for want of the board."""

    T_flange_sensor: Array
    residual_px: float
    residual_m: float
    std_m: Array
    std_rad: Array
    T_base_board: Array
    method_errors_px: dict[str, float]
    method: str
    n_views: int
    n_points: int
    n_missing: int

    def record(self) -> dict[str, Any]:
        """The method's own figures for the result JSON."""
        return {"residual_px": round(self.residual_px, 4),
                "hand_eye_heldout_px": {k: round(v, 4) for k, v in self.method_errors_px.items()},
                "hand_eye_method": self.method, "n_views_without_board": self.n_missing,
                "board_xyz_found_m": np.round(self.T_base_board[:3, 3], 6).tolist()}


def detect_board(image: Array, board: BoardConfig) -> tuple[Array, Array] | None:
    """The detected corners of ``board`` in a grey ``image``: board-frame points (N, 3) [m] and pixels
    (N, 2), or None when fewer than ``MIN_CORNERS`` are found."""
    cv2 = import_cv2()
    charuco = board.opencv()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(charuco).detectBoard(np.asarray(image, dtype=np.uint8))
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    obj = np.asarray(charuco.getChessboardCorners(), dtype=np.float64)[np.asarray(ids).ravel()]
    return obj, np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def load_board_views(folder: Path, board: BoardConfig) -> tuple[list[BoardView], int]:
    """The views of a job folder in which the board was found, and how many frames it was not found in
    (or that had no grey image)."""
    views, missing = [], 0
    for path in sorted((folder / "frames").glob("*.npz")):
        with np.load(path) as f:
            found = detect_board(f["intensity"], board) if "intensity" in f and "K" in f else None
            if found is None:
                missing += 1
                continue
            views.append(BoardView(np.array(f["T_base_flange"], dtype=np.float64), found[0], found[1],
                                   np.array(f["K"], dtype=np.float64)))
    return views, missing


def _board_in_camera(view: BoardView) -> Array:
    cv2 = import_cv2()
    ok, rvec, tvec = cv2.solvePnP(view.object_points, view.image_points, view.K, None)
    if not ok:
        raise CalibrationError("solvePnP failed on a view with the board found")
    return make_T(Rotation.from_rotvec(rvec.ravel()).as_matrix(), tvec.ravel())


def _board_in_base(views: Sequence[BoardView], T_cam_board: Sequence[Array], T_fs: Array) -> Array:
    """The mean over views of T_base_flange T_flange_sensor T_cam_board."""
    poses = [v.T_base_flange @ T_fs @ T for v, T in zip(views, T_cam_board, strict=True)]
    R = Rotation.from_matrix(np.stack([P[:3, :3] for P in poses])).mean().as_matrix()
    return make_T(R, np.mean([P[:3, 3] for P in poses], axis=0))


def _reprojection(views: Sequence[BoardView], T_fs: Array, T_base_board: Array) -> Array:
    """Pixel residuals (2 N,) of every corner of ``views``."""
    out = []
    for v in views:
        p = transform_points(inv_T(v.T_base_flange @ T_fs) @ T_base_board, v.object_points)
        uv = p[:, :2] / p[:, 2:3] * np.diag(v.K)[:2] + v.K[:2, 2]
        out.append((uv - v.image_points).ravel())
    return np.concatenate(out)


def _hand_eye(views: Sequence[BoardView], T_cam_board: Sequence[Array], method: str) -> Array:
    cv2 = import_cv2()
    flag = getattr(cv2, f"CALIB_HAND_EYE_{method.upper()}")
    R, t = cv2.calibrateHandEye([v.T_base_flange[:3, :3] for v in views],
                                [v.T_base_flange[:3, 3] for v in views], [T[:3, :3] for T in T_cam_board],
                                [T[:3, 3] for T in T_cam_board], method=flag)
    return make_T(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).ravel())


def fit_mount_to_board(views: Sequence[BoardView], n_missing: int = 0) -> BoardFit:
    """Solve the mount from board views (see the module docstring); ``CalibrationError`` with fewer than
    ``MIN_VIEWS`` views or an axis the views cannot observe."""
    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"the board was found in {len(views)} views ({n_missing} without it); at "
                               f"least {MIN_VIEWS} are needed")
    T_cam_board = [_board_in_camera(v) for v in views]
    held = [i % HOLD_BACK == HOLD_BACK - 1 for i in range(len(views))]
    train = [v for v, h in zip(views, held, strict=True) if not h]
    train_T = [T for T, h in zip(T_cam_board, held, strict=True) if not h]
    test = [v for v, h in zip(views, held, strict=True) if h]
    errors, candidates = {}, {}
    for method in HAND_EYE_METHODS:
        T_fs = _hand_eye(train, train_T, method)
        r = _reprojection(test, T_fs, _board_in_base(train, train_T, T_fs))
        errors[method] = float(np.sqrt(np.mean(r ** 2)))
        candidates[method] = T_fs
    best = min(errors, key=lambda k: errors[k])
    T0 = candidates[best]
    B0 = _board_in_base(views, T_cam_board, T0)

    def board(x: Array) -> Array:
        return make_T(Rotation.from_rotvec(x[N_MOUNT + 3:]).as_matrix() @ B0[:3, :3],
                      B0[:3, 3] + x[N_MOUNT:N_MOUNT + 3])

    def residuals(x: Array) -> Array:
        return _reprojection(views, mount_from_params(T0, x[:N_MOUNT]), board(x))

    sol = least_squares(residuals, np.zeros(N_MOUNT + 6), x_scale="jac")
    r = residuals(sol.x)
    std = mount_std(residuals, sol.x, r)
    T_fs = mount_from_params(T0, sol.x[:N_MOUNT])
    B = board(sol.x)
    depth = float(np.mean([(inv_T(v.T_base_flange @ T_fs) @ B)[2, 3] for v in views]))
    rms = float(np.sqrt(np.mean(r ** 2)))
    return BoardFit(T_flange_sensor=T_fs, residual_px=rms, residual_m=rms * depth / float(views[0].K[0, 0]),
                    std_m=std[:3], std_rad=std[3:], T_base_board=B, method_errors_px=errors, method=best,
                    n_views=len(views), n_points=r.size // 2, n_missing=n_missing)
