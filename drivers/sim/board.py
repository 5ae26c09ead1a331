"""A ChArUco calibration board: its definition (the cell file's ``calibration.board``) and, in sim, its
printed image lying flat on the table, which the simulated RGB-D camera sees in its intensity image.

Board frame: OpenCV's (``cv2.aruco.CharucoBoard``): origin at the board's top-left corner as printed, x
along the rows of squares, y down the columns, z into the board (so z points down into the table when
the board lies face up). The printed image covers ``squares_x * square_m`` by ``squares_y * square_m``.

OpenCV (``opencv-contrib-python-headless`` 4.x, the ``calibration`` extra; the 5.0 wheels have no
``calibrateHandEye``) is imported only when a board is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import model_validator

from drivers.config_base import CellCoordinate, CellSize, StrictModel, Turn
from drivers.errors import DriverError
from drivers.transforms import make_T

Array = NDArray[np.float64]

INSTALL_HINT = ("the ChArUco board needs OpenCV: pip install 'cell[calibration]' "
                "(opencv-contrib-python-headless 4.x)")
TEXTURE_PX_PER_SQUARE = 120
"""Resolution of the simulated board's printed image [px per square]."""
INCH_M = 0.0254
INTENSITY_TABLE = 110
INTENSITY_OBJECT = 170


def import_cv2() -> Any:
    """``cv2`` with its aruco module, or ``DriverError`` with the pip command that installs it."""
    try:
        import cv2
    except ImportError:
        raise DriverError(INSTALL_HINT, device="charuco board") from None
    if not hasattr(cv2, "aruco") or not hasattr(cv2, "calibrateHandEye"):
        raise DriverError(INSTALL_HINT, device="charuco board")
    return cv2


class BoardConfig(StrictModel):
    """A ChArUco board: ``squares`` (x, y) chessboard squares of ``square_m`` [m], markers of
    ``marker_m`` [m] from the predefined aruco ``dictionary``."""

    squares: tuple[int, int] = (7, 5)
    square_m: CellSize = 0.03
    marker_m: CellSize = 0.022
    dictionary: Literal["DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_5X5_100", "DICT_6X6_50",
                        "DICT_6X6_100"] = "DICT_5X5_100"

    @model_validator(mode="after")
    def _sizes(self) -> BoardConfig:
        if min(self.squares) < 3:
            raise ValueError(f"squares {self.squares}: at least 3 x 3")
        if self.marker_m >= self.square_m:
            raise ValueError(f"marker_m {self.marker_m} must be below square_m {self.square_m}")
        return self

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares[0] * self.square_m, self.squares[1] * self.square_m

    def opencv(self) -> Any:
        """The ``cv2.aruco.CharucoBoard``."""
        cv2 = import_cv2()
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_m, dictionary)


class SimBoardConfig(StrictModel):
    """In sim: the cell's ``calibration.board`` lies face up on the table, its centre at ``pose``
    (x [m], y [m], yaw [deg]) from the station."""

    pose: tuple[CellCoordinate, CellCoordinate, Turn] = (0.0, 0.0, 0.0)
    """[m, m, deg] the board centre's x, y from the station and its yaw."""


@dataclass(frozen=True)
class TableTexture:
    """A printed image (H, W) uint8 lying face up on the table: ``T_base_board`` places the board frame
    (see the module docstring), ``size_m`` (x, y) the printed area [m]."""

    image: NDArray[np.uint8]
    T_base_board: Array
    size_m: tuple[float, float]

    def intensity(self, points_base: Array) -> NDArray[np.uint8]:
        """The printed intensity at table points (N, 3) [m, base frame]; the table's own outside."""
        R, t = self.T_base_board[:3, :3], self.T_base_board[:3, 3]
        local = (points_base - t) @ R
        h, w = self.image.shape
        u = np.floor(local[:, 0] / self.size_m[0] * w).astype(np.int64)
        v = np.floor(local[:, 1] / self.size_m[1] * h).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out = np.full(points_base.shape[0], INTENSITY_TABLE, dtype=np.uint8)
        out[inside] = self.image[v[inside], u[inside]]
        return out


def board_image(board: BoardConfig, px_per_square: int, margin_px: int = 0) -> NDArray[np.uint8]:
    """The board's image, ``px_per_square`` pixels to a chessboard square, in a white margin of
    ``margin_px`` pixels (OpenCV's ``CharucoBoard.generateImage``; markers with a one-bit border)."""
    px = (board.squares[0] * px_per_square + 2 * margin_px, board.squares[1] * px_per_square + 2 * margin_px)
    return np.asarray(board.opencv().generateImage(px, marginSize=margin_px, borderBits=1), dtype=np.uint8)


def board_texture(board: BoardConfig, T_base_board: Array) -> TableTexture:
    """The board's printed image (``TEXTURE_PX_PER_SQUARE``) at ``T_base_board``."""
    return TableTexture(image=board_image(board, TEXTURE_PX_PER_SQUARE), T_base_board=T_base_board,
                        size_m=board.size_m)


@dataclass(frozen=True)
class PrintableBoard:
    """A board's image to print (:func:`printable_board`): ``dpi`` [px per inch] at which it prints at
    the board's size, ``size_m`` (x, y) the printed image with its margin [m]."""

    image: NDArray[np.uint8]
    dpi: float
    size_m: tuple[float, float]


def printable_board(board: BoardConfig, dpi: float = 300.0, margin_m: float = 0.01) -> PrintableBoard:
    """The image of ``board`` to print at 100 % scale, about ``dpi`` pixels per inch with a white margin of
    ``margin_m`` [m]: a whole number of pixels to a square, and the exact resolution at which a square
    prints ``square_m`` wide (a PNG stores it; a printer told to fit the page scales it)."""
    px_per_square = max(1, round(board.square_m * dpi / INCH_M))
    px_per_m = px_per_square / board.square_m
    margin_px = round(margin_m * px_per_m)
    image = board_image(board, px_per_square, margin_px)
    return PrintableBoard(image=image, dpi=px_per_m * INCH_M,
                          size_m=(image.shape[1] / px_per_m, image.shape[0] / px_per_m))


def board_on_table(board: BoardConfig, station_xy: tuple[float, float], table_z: float,
                   pose: tuple[float, float, float]) -> Array:
    """T_base_board of the board lying face up (board z down) with its centre at ``pose`` (x, y,
    yaw_deg) from the station on the table at ``table_z`` [m]."""
    yaw = np.deg2rad(pose[2])
    c, s = np.cos(yaw), np.sin(yaw)
    # board x along the yawed base x, board y along the yawed base -y, board z down: a right-handed frame
    R = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])
    centre = np.array([station_xy[0] + pose[0], station_xy[1] + pose[1], table_z])
    half = np.array([board.size_m[0] / 2.0, board.size_m[1] / 2.0, 0.0])
    return make_T(R, centre - R @ half)
