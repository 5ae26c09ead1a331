"""path.png: the sensor's path from home, with the scan's start (its first capture) marked apart."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg

from cell.planning.path_plot import FIRST_CAPTURE_LABEL, HOME_LABEL, path_figure, plot_path


def _markers(fig):
    """Legend label -> marked position (3,) [m] of the figure's single-point scatters."""
    ax = fig.axes[0]
    out = {}
    for c in ax.collections:
        xs, ys, zs = c._offsets3d
        if len(xs) == 1:
            out[c.get_label()] = np.array([xs[0], ys[0], zs[0]], dtype=float)
    return out


def test_the_path_marks_home_and_the_first_capture_apart(tmp_path):
    """A servo scan's path: from home (z 0.5 m) to the start view, where the first capture is taken and
    the scan starts (the paper's Fig. 3 starts there), then around the object."""
    home = np.array([0.3, 0.0, 0.5])
    start_view = np.array([0.45, -0.22, 0.19])
    approach = np.linspace(home, start_view, 20)
    around = start_view + np.column_stack([np.linspace(0.0, 0.2, 30), np.zeros(30), np.zeros(30)])
    path = np.vstack([approach, around])
    fig = path_figure(path, np.array([0.45, 0.0, 0.08]), first_capture_base=start_view)
    marked = _markers(fig)
    np.testing.assert_allclose(marked[HOME_LABEL], home)
    np.testing.assert_allclose(marked[FIRST_CAPTURE_LABEL], start_view)
    assert "start" not in marked  # no marker that a reader could take for the scan's start at home
    assert {t.get_text() for t in fig.axes[0].get_legend().get_texts()} >= {HOME_LABEL, FIRST_CAPTURE_LABEL}
    plot_path(tmp_path / "path.png", path, None, first_capture_base=start_view)
    assert (tmp_path / "path.png").read_bytes()[:4] == b"\x89PNG"


def test_a_path_without_a_capture_marks_home_only():
    marked = _markers(path_figure(np.array([[0.3, 0.0, 0.5], [0.4, 0.0, 0.4]]), None))
    assert HOME_LABEL in marked and FIRST_CAPTURE_LABEL not in marked


def _servo_path() -> tuple[np.ndarray, np.ndarray]:
    """A path from home (z 0.5 m) down to a start view and 0.4 m along x: far longer than it is wide."""
    home, start_view = np.array([0.3, 0.0, 0.5]), np.array([0.25, -0.2, 0.15])
    around = start_view + np.column_stack([np.linspace(0.0, 0.4, 30), np.zeros(30), np.zeros(30)])
    return np.vstack([np.linspace(home, start_view, 20), around]), start_view


def test_the_path_is_drawn_to_one_scale_on_every_axis():
    """A metre along x looks as long as a metre along y or z: the path around the object keeps its shape
    (matplotlib's default box, 4:4:3 on each axis's own data range, had stretched a 0.2 m span as far as
    a 0.4 m one)."""
    path, start_view = _servo_path()
    fig = path_figure(path, np.array([0.45, 0.0, 0.08]), first_capture_base=start_view)
    ax = fig.axes[0]
    spans = np.array([np.ptp(ax.get_xlim3d()), np.ptp(ax.get_ylim3d()), np.ptp(ax.get_zlim3d())])
    box = np.asarray(ax.get_box_aspect(), dtype=float)
    np.testing.assert_allclose(box / box[0], spans / spans[0], rtol=1e-6)
    assert "base frame" in ax.get_title()


def test_every_axis_label_is_inside_the_image():
    """The z axis's label was cut at the image's right edge (``z [m`` in path.png)."""
    path, start_view = _servo_path()
    fig = path_figure(path, np.array([0.45, 0.0, 0.08]), first_capture_base=start_view)
    canvas = FigureCanvasAgg(fig)  # what savefig renders a PNG with
    canvas.draw()
    renderer = canvas.get_renderer()
    ax = fig.axes[0]
    inside = fig.bbox
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        label = axis.label.get_window_extent(renderer)
        assert label.x0 >= inside.x0 and label.x1 <= inside.x1, axis.label.get_text()
        assert label.y0 >= inside.y0 and label.y1 <= inside.y1, axis.label.get_text()
