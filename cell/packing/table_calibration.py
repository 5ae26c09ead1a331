"""The scan's own calibration residual, measured on the table that every capture sees.

A calibrated cell still gets its sensor's pose a little wrong: the hand-eye calibration leaves an error
of the mount (for the ToF cell's shape calibration about 1.5 mm and 0.15 deg per axis, the sizes of
``drivers.sim.errors``), and every range carries the common offset left after ``cell calibrate tof``. The
same mount error holds in every capture of a scan, but it moves the points of captures taken from
different sides in different directions in the base frame, so the object's faces come apart between
views and its box grows or shrinks by millimetres (on the packing grid's flange and gripper scans this
error, more than the range noise, kept the estimate from 1 cm: ``benchmarks/packing_error_sources.py``).

The table is the one surface whose place is known (the plane z = ``table_z``, the station's calibration)
and every capture sees it around the object. The believed pose of a capture is (R, o) in the base frame
and a table point of it lies at s = r d in the sensor frame (range r along the unit ray d). When the
sensor really sat at the mount times (exp(omega), t) (omega a rotation vector, t a translation, both in
the sensor frame) and reported every range long by b, the point really lies at
R (exp(omega) (r - b) d + t) + o, on the table. To first order in (omega, t, b), with a = R^T e_z the
table's normal in the sensor frame, that reads, per table point,

    table_z - p_z = (s x a) . omega + a . t - (a . d) b,

one linear equation in x = (omega, t, b) (7) with the point's range noise along z, sigma(r) |a . d|, as
its noise. :func:`table_correction` solves them all, over all captures, by weighted least squares with
the calibration's own residual as a zero-mean Gaussian prior on x (the packing error model's
``pose_rad``, ``pose_m`` and ``bias_m``): the maximum a posteriori correction. What
the table cannot tell stays at the prior's zero: the translation along an image axis that stays level in
every view, and a rotation about the table's normal. A table point more than ``OUTLIER_SIGMAS`` of its
std off the fitted plane (a part of the object low enough to pass for the table, a zone mixing the
object's edge and the table) is left out and the fit repeated, ``FIT_ROUNDS`` times in all.

Not all of the pose error is common to the captures: the arm's joints' zero offsets move the flange
differently in every configuration (the error model's ``capture_pose_m`` and ``capture_pose_rad``, a
calibrated arm's 0.4 mm and 0.5 mrad). Each capture's table points therefore share an error of their own,
u_c (6: a rotation and a translation, in the sensor frame as omega and t), which more points of that
capture do not average out. It enters as (omega, t) does, with that zero-mean Gaussian prior, and the fit
takes it out capture by capture (its posterior given x, Woodbury's identity on the capture's 6 x 6
block), so that x rests on what the captures agree on. Without it a camera's thousands of table points a
capture, each within a millimetre, pinned x to the captures' own errors: an image axis nearly level in
every view has a small a_x, and the translation along it came out 13-48 mm on the camera cell's LR-NBV
scans (a prior of 2 mm), which moved the flange's box 9 cm wide.

The table points are those a capture saw within the segmentation's table cut and outside the footprint of
the object's extent (the box of every ROI): ``cell.packing.table_band.on_table``, on which a capture's
table level is taken too. The captures' own errors are taken out of the fit, not out of the captures:
they stay in the residual, which the upper bound allows for (``pose_m``, ``pose_rad``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.packing.objects import extent_box
from cell.packing.table_band import on_table
from cell.packing.uncertainty import ErrorModel, Sighting
from cell.perception.pipeline import PerceptionPipeline

Array = NDArray[np.float64]

# A table point further off the fitted plane than this many of its std is not the table's: a plane's
# points lie that far once in 370.
OUTLIER_SIGMAS = 3.0
# Fits in all: the first on every table point, each next one without the outliers of the one before.
FIT_ROUNDS = 3
# A capture with fewer table points than this adds nothing (a view down onto the object alone).
MIN_TABLE_POINTS = 10


@dataclass(frozen=True)
class TableCorrection:
    """The sensor's pose error in every capture of a scan, as the table showed it: the true sensor frame
    is the believed one times (``rotation_vector`` (3,) [rad], ``translation_m`` (3,) [m]), both in the
    sensor frame, and every range was reported ``range_offset_m`` [m] long; ``n_table_points`` the table
    points it was measured on (0: none, the correction is zero)."""

    rotation_vector: Array
    translation_m: Array
    range_offset_m: float
    n_table_points: int

    @staticmethod
    def none() -> TableCorrection:
        return TableCorrection(np.zeros(3), np.zeros(3), 0.0, 0)

    def transform(self) -> Array:
        """The true sensor frame in the believed one (4, 4)."""
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(self.rotation_vector).as_matrix()
        T[:3, 3] = self.translation_m
        return T

    def apply(self, sighting: Sighting) -> Sighting:
        """``sighting`` where the sensor really was: its points moved back along their rays by the range
        offset and carried by the pose error, its pose the true one (the module docstring), the ends of
        its free rays carried along."""
        T = sighting.T_base_sensor
        T_true = T @ self.transform()
        local = (sighting.points - T[:3, 3]) @ T[:3, :3]
        ranges = np.linalg.norm(local, axis=1, keepdims=True)
        local = local * (1.0 - self.range_offset_m / np.maximum(ranges, 1e-9))
        free = (sighting.free_ends - T[:3, 3]) @ T[:3, :3]
        return Sighting(T_true, *(p @ T_true[:3, :3].T + T_true[:3, 3] for p in (local, free)))

    def summary(self) -> dict[str, object]:
        """For result.json: the correction in deg and mm (rounded) and the table points it rests on."""
        return {"rotation_deg": np.round(np.rad2deg(self.rotation_vector), 3).tolist(),
                "translation_mm": np.round(1e3 * self.translation_m, 2).tolist(),
                "range_offset_mm": round(1e3 * self.range_offset_m, 2),
                "n_table_points": self.n_table_points}


def table_correction(perception: PerceptionPipeline, sightings: list[Sighting],
                     model: ErrorModel) -> TableCorrection:
    """The maximum a posteriori :class:`TableCorrection` of the scan whose captures are ``sightings``
    (base frame), from their table points (the module docstring); zero without a ROI or table points."""
    if extent_box(perception) is None:  # no object yet: nothing tells the table from it
        return TableCorrection.none()
    rows: list[Array] = []
    heights: list[Array] = []
    sigmas: list[Array] = []
    for s in sightings:
        R, origin = s.T_base_sensor[:3, :3], s.T_base_sensor[:3, 3]
        table = on_table(perception, s.points)
        if np.count_nonzero(table) < MIN_TABLE_POINTS:
            continue
        p = s.points[table]
        local = (p - origin) @ R
        rays = local / np.linalg.norm(local, axis=1, keepdims=True)
        up = R[2]  # the base frame's z axis in the sensor frame (a row of R = a column of R^T)
        rows.append(np.hstack([np.cross(local, up), np.broadcast_to(up, local.shape), -(rays @ up)[:, None]]))
        heights.append(perception.table_z_m - p[:, 2])
        sigmas.append(model.range_sigma(np.linalg.norm(local, axis=1)) * np.abs(rays @ up))
    if not rows:
        return TableCorrection.none()
    weights = [1.0 / np.maximum(sigma, 1e-6) ** 2 for sigma in sigmas]
    prior = np.diag(1.0 / np.maximum([model.pose_rad] * 3 + [model.pose_m] * 3 + [model.bias_m], 1e-9) ** 2)
    capture_prior = np.diag(1.0 / np.maximum([model.capture_pose_rad] * 3 + [model.capture_pose_m] * 3,
                                             1e-9) ** 2)
    inliers = [np.ones(y.size, dtype=bool) for y in heights]
    x: Array = np.zeros(7)
    for _ in range(FIT_ROUNDS):
        information, gradient = prior.copy(), np.zeros(7)
        blocks = []
        for J, y, w, keep in zip(rows, heights, weights, inliers, strict=True):
            Jw = J[keep] * w[keep, None]
            A, g = J[keep].T @ Jw, Jw.T @ y[keep]
            # the capture's own error u_c enters through the first 6 columns: marginalised out
            S = np.linalg.inv(capture_prior + A[:6, :6])
            information += A - A[:, :6] @ S @ A[:6, :]
            gradient += g - A[:, :6] @ S @ g[:6]
            blocks.append((S, A, g))
        x = np.asarray(np.linalg.solve(information, gradient), dtype=np.float64)
        for c, ((S, A, g), J, y, w) in enumerate(zip(blocks, rows, heights, weights, strict=True)):
            u = S @ (g[:6] - A[:6, :] @ x)  # the capture's own error, given x
            inliers[c] = np.abs(y - J @ x - J[:, :6] @ u) * np.sqrt(w) <= OUTLIER_SIGMAS
    n_inliers = sum(int(np.count_nonzero(keep)) for keep in inliers)
    return TableCorrection(x[:3], x[3:6], float(x[6]), n_inliers)


def corrected_perception(perception: PerceptionPipeline, sightings: list[Sighting]) -> PerceptionPipeline:
    """A pipeline of ``perception``'s configuration into which the captures ``sightings`` (as the table
    correction leaves them) were accumulated in order (``PerceptionPipeline.add_capture``): the scan's
    cloud, occupancy map, object and ROIs where the corrected captures put them. With a zero correction
    they are the scan's own."""
    rebuilt = perception.empty_like(np.random.default_rng(perception.config.segmentation.seed))
    for s in sightings:
        rebuilt.add_capture(s.T_base_sensor, s.points, s.free_ends)
    return rebuilt
