"""The evaluation report as a reader compares planners on it: a planner keeps one colour in every panel
of fig5.png and fig3.png, and the scans a time budget cut short are named."""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure

from cell.evaluation.report import fig3_figure, fig5_figure, groups, write_report
from cell.evaluation.results import row_from_result
from cell.evaluation.spec import ScanSpec
from tests.result_rows import result_row

CONFIG = Path(__file__).resolve().parents[1] / "config" / "sim-ur5e-tof.yaml"


def _rows() -> list[dict[str, str]]:
    """A cube scanned by heu and lr-nbv, and a box by lr-nbv only (its heu scans failed): lr-nbv is the
    second planner of the cube's group and the first of the box's."""
    def row(obj: str, planner: str, seed: int) -> dict[str, str]:
        return result_row(obj, planner, seed, coverage_pct=f"{40 + seed:.4f}", chamfer_mm="5.0000",
                          scan_time_s=f"{20 + seed:.4f}", iou="0.8000", packing_coverage_pct="60.0000",
                          n_poses="9", n_useless_poses="1", dims_m="0.1000 0.1000 0.1000",
                          dims_true_m="0.1000 0.1000 0.1000")
    failed = [{**row("horizontal_box", "heu", seed), "status": "failed"} for seed in (0, 1)]
    return [row(obj, planner, seed) for obj, planners in (("cube", ("heu", "lr-nbv")),
                                                          ("horizontal_box", ("lr-nbv",)))
            for planner in planners for seed in (0, 1)] + failed


def _colours(fig: Figure) -> dict[str, set[str]]:
    """Planner -> the colours its dots, curves and bars have in the figure's panels: the labelled lines
    and bars of a legend, and the bars of a panel whose x ticks name the planners."""
    FigureCanvasAgg(fig).draw()  # lays out the planners' tick labels
    found: dict[str, set[str]] = {}
    for ax in fig.axes:
        for line in ax.get_lines():
            if not line.get_label().startswith("_"):
                found.setdefault(line.get_label(), set()).add(to_hex(line.get_color()))
        ticks = [t.get_text() for t in ax.get_xticklabels()]
        for bars in ax.containers:
            if not bars.get_label().startswith("_"):  # a legend's: L, W, H of one planner
                found.setdefault(bars.get_label(), set()).update(to_hex(p.get_facecolor()) for p in bars)
            else:  # one bar per planner, named by its tick
                for tick, patch in zip(ticks, bars, strict=True):
                    found.setdefault(tick, set()).add(to_hex(patch.get_facecolor()))
    return found


def test_a_planner_has_one_colour_in_every_panel_of_both_figures():
    """fig3.png's lower panels drew every planner's bar blue under a legend giving lr-nbv orange, and a
    planner's colour followed its place in each group, so lr-nbv was orange for the cube and blue for
    the box."""
    gs = groups(_rows())
    fig3, fig5 = _colours(fig3_figure(gs)), _colours(fig5_figure(gs, {}))
    assert set(fig3) == set(fig5) == {"heu", "lr-nbv"}
    for planner in ("heu", "lr-nbv"):
        assert len(fig3[planner] | fig5[planner]) == 1, (planner, fig3[planner], fig5[planner])
    assert fig3["heu"] != fig3["lr-nbv"]


def test_the_report_lists_the_scans_that_their_time_budget_cut_short(tmp_path):
    """A grid run with --max-time 40: lr-nbv ran out of time (result.json's limit_reached), heu ended on
    its own; the report said only "2 completed", and the comparison read as of two finished scans."""
    rows = [result_row("cube", "heu", 0, coverage_pct="1.6000", limit_reached="false",
                       termination="heu complete: 13 of 13 poses captured, 0 refused"),
            result_row("cube", "lr-nbv", 0, coverage_pct="3.3000", limit_reached="true",
                       termination="time budget of 40 s used up"),
            result_row("cube", "vs-local", 0, status="failed", limit_reached="true", termination="fault")]
    md = (write_report(rows, tmp_path, {})).read_text()
    cut = md.split("**Cut short**: ", 1)[1].split("\n\n")
    assert cut[0].startswith("1 of the 2 scans in the figures ended on a limit of the job")
    assert cut[1] == "- cube 0,0,0 lr-nbv seed 0: completed: time budget of 40 s used up"
    # a grid whose scans all ended on their own (or whose folders do not say) has no such paragraph
    md = write_report([{**r, "limit_reached": flag} for r, flag in zip(rows[:2], ("false", ""), strict=True)],
                      tmp_path, {}).read_text()
    assert "Cut short" not in md


def test_results_csv_says_whether_a_limit_ended_the_scan():
    spec = ScanSpec(str(CONFIG), "cube", (0.0, 0.0, 0.0), "lr-nbv", 0)
    result = {"status": "completed", "termination": "time budget of 40 s used up", "limit_reached": True}
    assert row_from_result(spec, result)["limit_reached"] == "true"
    assert row_from_result(spec, {**result, "limit_reached": False})["limit_reached"] == "false"
    del result["limit_reached"]  # a folder of a release before the flag
    assert row_from_result(spec, result)["limit_reached"] == ""
