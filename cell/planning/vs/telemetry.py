"""The servo planners' outputs for a job folder: the time series of the visual-servoing paper's Fig. 4 as
CSV and as a four-panel PNG, and the sensor path around the object as in Fig. 3 (left).

H_ROI is in the form the planner's termination judges (``planners.vs.objective.entropy``), which the CSV's
column and the panel's label name: ``h_roi_nats`` for eq. 12 as written, ``h_roi_observation_aware_nats``
for the observation-aware form (``cell.perception.entropy_form``).

In sim the coverage of the ground truth (eq. 13 of the cloud as it stands at each capture, before the
ground truth is registered to it; known only to the job, not to the planner) is added: a column of the
CSV, and a second axis on the H_ROI panel."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure  # not pyplot: files only, no display or global figure state

from cell.perception.entropy_form import EntropyForm, h_roi_name
from cell.planning.base import Array
from cell.planning.path_plot import PATH_NAME, plot_path
from cell.planning.vs.servo_scan import TelemetryRow

CSV_NAME = "servo.csv"
FIG4_NAME = "servo.png"
H_ROI_COLUMNS: dict[EntropyForm, str] = {"paper": "h_roi_nats",
                                         "observation_aware": "h_roi_observation_aware_nats"}
"""The CSV column of H_ROI in each form."""


def coverage_at(t: Array, coverage: Sequence[tuple[float, float]]) -> Array:
    """Coverage [%] in force at each time of ``t`` [s]: the value of the last ``(time [s], coverage [%])``
    sample at or before it (NaN before the first)."""
    if not coverage:
        return np.full(len(t), np.nan)
    times, values = (np.array(c, dtype=float) for c in zip(*coverage, strict=True))
    idx = np.searchsorted(times, t, side="right") - 1
    return np.where(idx >= 0, values[np.maximum(idx, 0)], np.nan)


def write_telemetry_csv(path: Path, rows: Sequence[TelemetryRow], h_roi_entropy: EntropyForm,
                        coverage: Sequence[tuple[float, float]] = ()) -> None:
    """``t,e_norm_m,f_nats,g_norm,<H_ROI>,mode`` and, with ``coverage`` samples, ``coverage_pct``: one line
    per servo iteration (H_ROI and coverage empty before their first value), H_ROI's column named by its
    form ``h_roi_entropy`` (``H_ROI_COLUMNS``)."""
    cov = coverage_at(np.array([r.t for r in rows]), coverage) if coverage else None
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "e_norm_m", "f_nats", "g_norm", H_ROI_COLUMNS[h_roi_entropy], "mode"]
                   + (["coverage_pct"] if cov is not None else []))
        for i, r in enumerate(rows):
            line = [f"{r.t:.4f}", f"{r.e_norm:.6g}", f"{r.f:.6g}", f"{r.g_norm:.6g}",
                    "" if r.h_roi is None else f"{r.h_roi:.6g}", r.mode]
            if cov is not None:
                line.append("" if np.isnan(cov[i]) else f"{cov[i]:.2f}")
            w.writerow(line)


def plot_fig4(path: Path, rows: Sequence[TelemetryRow], h_roi_entropy: EntropyForm,
              coverage: Sequence[tuple[float, float]] = ()) -> None:
    """:func:`servo_figure` saved as a PNG at ``path``."""
    servo_figure(rows, h_roi_entropy, coverage).savefig(path, dpi=100)


def servo_figure(rows: Sequence[TelemetryRow], h_roi_entropy: EntropyForm,
                 coverage: Sequence[tuple[float, float]] = ()) -> Figure:
    """Four panels over job time: ||e|| (eq. 2), f(r) (eq. 9), ||g|| before clipping (eq. 4; g is
    dimensionless: VS-Local's relative gradient times ``alpha`` [m], VS-Global's scaled unit tangent), H_ROI
    (eq. 12, labelled with its form ``h_roi_entropy``), the last with the coverage [%] on a second axis when
    ``coverage`` samples are given."""
    t = np.array([r.t for r in rows])
    series = [("||e|| [m]", [r.e_norm for r in rows]), ("f(r) [nats]", [r.f for r in rows]),
              ("||g|| before clipping [1]", [r.g_norm for r in rows]),
              (f"{h_roi_name(h_roi_entropy)} [nats]", [np.nan if r.h_roi is None else r.h_roi for r in rows])]
    fig = Figure(figsize=(10, 6))
    axes = fig.subplots(2, 2, sharex=True)
    for ax, (label, values) in zip(axes.ravel(), series, strict=True):
        ax.plot(t, values, lw=1.0)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("t [s]")
    fig.suptitle("Servo telemetry over the job's time (paper Fig. 4)")
    if coverage:
        twin = axes[1, 1].twinx()
        twin.plot(t, coverage_at(t, coverage), lw=1.0, color="tab:green")
        twin.set_ylabel("coverage, unregistered [%]", color="tab:green")
    fig.tight_layout()
    return fig


def write_servo_outputs(folder: Path, rows: Sequence[TelemetryRow], h_roi_entropy: EntropyForm,
                        positions_base: Array, centroid_base: Array | None,
                        coverage: Sequence[tuple[float, float]] = (),
                        first_capture_base: Array | None = None) -> None:
    """``servo.csv``, ``servo.png`` (Fig. 4) and ``path.png`` (Fig. 3, left, its scan starting at
    ``first_capture_base`` [m, base frame] when given) in a job folder; ``h_roi_entropy``: the form of the
    rows' H_ROI; ``coverage``: (job time [s], coverage [%]) samples, in sim."""
    write_telemetry_csv(folder / CSV_NAME, rows, h_roi_entropy, coverage)
    plot_fig4(folder / FIG4_NAME, rows, h_roi_entropy, coverage)
    plot_path(folder / PATH_NAME, positions_base, centroid_base, first_capture_base=first_capture_base)
