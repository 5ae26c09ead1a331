"""The sensor's path around the object as a job folder's ``path.png`` (the visual-servoing paper's Fig. 3,
left), for every planner: a servo planner's continuous path, or a view planner's moves between the views
it captured from, those marked.

The path starts at home, where the job starts, and the scan starts later, at its first capture (a servo
planner's start view, a view planner's first view): the paper's Fig. 3 starts there. Both are marked and
named, so that the move from home to the first view is not read as part of the scan."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # not pyplot: files only, no display or global figure state
from matplotlib.ticker import MaxNLocator

from cell.planning.base import Array

PATH_NAME = "path.png"
HOME_LABEL = "home (job start)"
FIRST_CAPTURE_LABEL = "first capture (scan start)"
TITLE = "sensor path in the robot base frame"
ZOOM = 0.8
"""The 3D box's size in its axes (matplotlib's 1 put the z axis's label outside the image)."""


def path_figure(positions_base: Array, centroid_base: Array | None, captures_base: Array | None = None,
                first_capture_base: Array | None = None) -> Figure:
    """The sensor positions (N, 3) [m] in the base frame, in 3D, from home (the first) to the end, with the
    object centroid (3,) [m], the positions (K, 3) [m] captures were taken from and the sensor position
    (3,) [m] of the first capture, each when given."""
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    p = np.asarray(positions_base, dtype=float).reshape(-1, 3)
    ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=1.0)
    if captures_base is not None and len(captures_base):
        c = np.asarray(captures_base, dtype=float).reshape(-1, 3)
        ax.scatter(c[:, 0], c[:, 1], c[:, 2], marker=".", s=30, color="tab:blue", label=f"{len(c)} captures")
    if p.shape[0]:
        ax.scatter(*p[0], marker="s", color="grey", label=HOME_LABEL)
    if first_capture_base is not None:
        ax.scatter(*np.asarray(first_capture_base, dtype=float), marker="o", color="black",
                   label=FIRST_CAPTURE_LABEL)
    if p.shape[0]:
        ax.scatter(*p[-1], marker="x", label="end")
    if centroid_base is not None:
        ax.scatter(*np.asarray(centroid_base, dtype=float), marker="*", s=80, label="object centroid")
    _one_scale(ax)
    ax.set_title(TITLE)
    ax.set_xlabel("x [m]", labelpad=8)
    ax.set_ylabel("y [m]", labelpad=8)
    ax.set_zlabel("z [m]", labelpad=8)
    ax.legend(loc="upper left")
    fig.tight_layout()
    return fig


def _one_scale(ax: Any) -> None:  # an Axes3D: mplot3d has no type hints
    """Give ``ax`` (3D) one scale [m per pixel] on its three axes, over the range of what it plots:
    matplotlib's default box (4:4:3 over each axis's own range) stretches a short span as far as a long
    one, so a path's shape around the object is not what the sensor flew. ``ZOOM`` leaves room for the z
    axis's label, which the full-size box pushed past the image's right edge."""
    lo, hi = (np.array(v, dtype=float) for v in zip(ax.get_xlim3d(), ax.get_ylim3d(), ax.get_zlim3d(),
                                                     strict=True))
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-6)), zoom=ZOOM)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):  # a short axis's ticks otherwise run into its label
        axis.set_major_locator(MaxNLocator(5))


def plot_path(path: Path, positions_base: Array, centroid_base: Array | None,
              captures_base: Array | None = None, first_capture_base: Array | None = None) -> None:
    """:func:`path_figure` written to ``path`` as a PNG."""
    path_figure(positions_base, centroid_base, captures_base, first_capture_base).savefig(path, dpi=100)
