"""path.png: the sensor's path from home, with the scan's start (its first capture) marked apart."""

from __future__ import annotations

import numpy as np

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
