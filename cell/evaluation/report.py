"""``report.md`` and its figures, from ``results.csv`` and the re-processed scans' timelines (so a report
can be rebuilt from the output folder at any time).

Scans group by object and placement (the placement shown only where an object has several); within a
group, by planner. Only scans that ran to their end count (status ``completed`` or ``no_object``): a
failed scan, one whose re-process failed and one stopped (a protective stop: partial figures) are left
out of the tables, the tests, the figures and ``n``, and listed with their reasons under "Scans that did
not complete". A group's figures are the mean and standard error of the mean over its scans that
have the figure, ``mean ± se`` (no ``± se`` for one scan), the paper's figure in brackets where it has
one (the text says so only when one appears): Table I's in an object's row, and the paper's means over
its objects (scan time and path, section III-C) in a row per planner of the mean over the grid's
objects (``mean over N objects``), never in an object's row.

The sentence before each table says what its coverage figures are and within what radius:
``coverage %``, eq. 13 of the visual-servoing paper (within ``COVERAGE_RADIUS_M`` of a point of the
cloud), and ``surface reconstructed %``, the packing paper's surface coverage (within
``packing.coverage_radius_m`` of an object voxel's centre, ``cell.packing.result``), and why the two
differ widely on a sparse cloud. The packing section (``packing``: the grid's choice; Table I's report
leaves it out, a line saying results.csv holds those figures) quotes the packing paper's claims only
when the grid has one of its objects and planners, and gives the ground-truth box (sim), the mean upper
bound and the containers chosen. Each figure's better direction (higher or lower) is written under its
table and on its axis. Mann-Whitney U (two-sided; its p exact for small samples, ties included:
:data:`EXACT_SPLITS`) compares every two planners of a group on each figure both have (with the packing
section, its figures and each box dimension too); ``-`` where it cannot say anything (a single seed, or
all values tie); beside each test the smallest p its sample sizes can give
(:func:`smallest_p`), and the report says when that is not below 0.05: such a test cannot find a
difference whatever the values.

Scans in the figures that their time budget ended before their planner's own termination
(``limit_reached``) are listed under the counts ("Cut short"): their figures are of a scan cut short.

Figures: ``fig5.png`` (the visual-servoing paper's Fig. 5: each scan's Chamfer distance and coverage
against its scan time, a panel per group: a curve as the scan went on for a re-processed scan, from its
job folder's ``result_hires.json``, a dot where each scan ended, Table I's coverage dashed) and, with
the packing section, ``fig3.png`` (the packing paper's Fig. 3: the box's L, W, H with the ground truth marked
in sim, IoU, packing coverage, poses and useless poses per planner, mean and standard error, a column per
group). Each axis says whether higher or lower is better; a planner has one colour in every panel of
both figures (:func:`planner_colours`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure  # not pyplot: files only, no display
from scipy.stats import PermutationMethod, mannwhitneyu

from cell.evaluation import paper
from cell.evaluation.results import Row, RowId, Timeline, row_id, value
from cell.perception.metrics import COVERAGE_RADIUS_M, N_GROUND_TRUTH_POINTS
from drivers.atomic_file import atomic_path, write_text_atomic

REPORT_MD = "report.md"
FIG5 = "fig5.png"
FIG3 = "fig3.png"

# Groups side by side in a figure before it wraps to another band of panels below.
GROUPS_PER_ROW = 5
# (column, heading, decimals) of the two tables
RECONSTRUCTION = (("coverage_pct", "coverage %", 1), ("chamfer_mm", "Chamfer mm", 1),
                  ("hausdorff_mm", "Hausdorff mm", 1), ("scan_time_s", "scan time s", 1),
                  ("path_m", "path m", 2), ("coverage_unregistered_pct", "unregistered coverage %", 1))
PACKING = (("iou", "IoU", 3), ("packing_coverage_pct", "surface reconstructed %", 1), ("n_poses", "poses", 1),
           ("n_useless_poses", "useless poses", 1))
DIMS = ("L m", "W m", "H m")
Limits = dict[tuple[str, str], float]
"""Coverage limit [%] by (object, placement) as results.csv writes them."""
TESTED = ("coverage_pct", "chamfer_mm", "hausdorff_mm", "scan_time_s")
PACKING_TESTED = ("iou", "n_poses", "n_useless_poses")
"""The figures Mann-Whitney U compares: of the reconstruction table, and of the packing section (with the
box dimensions) where the report has it."""
PAPER_MEANS = ("scan_time_s", "path_m")
"""The figures the visual-servoing paper gives as a mean over its objects (section III-C), not per object."""
HIGHER_IS_BETTER = ("coverage_pct", "coverage_unregistered_pct", "iou", "packing_coverage_pct")
"""The figures of which more is better; of every other one of the tables, less is (errors, time, path,
poses); the box dimensions are best at the truth."""
SIGNIFICANCE = 0.05
"""The p below which a test's difference would be called significant."""
EXACT_SPLITS = 20_000
"""Up to this many ways of splitting two samples' pooled values into them (8 against 8 has 12870),
Mann-Whitney U's p is exact: twice the smaller share of splits whose U is at least or at most the samples'
(a permutation test, ties included, at most 1); beyond, it is the normal approximation with scipy's tie
correction, which with small tied samples (pose counts over five seeds) gave p about half the exact one:
0.027 for [1, 1, 1, 2, 2] against [2, 2, 3, 3, 3], where every split gives 0.048."""


@dataclass(frozen=True)
class Group:
    """The scans of one object at one placement: its label in the tables and rows by planner."""

    label: str
    object: str
    placement: str
    by_planner: dict[str, list[Row]]


MEASURED = ("completed", "no_object")
"""The statuses of scans that ran to their end: the ones a report's figures are of."""


def groups(rows: Sequence[Row]) -> list[Group]:
    """The rows (results.csv's order) of the scans that ran to their end (``MEASURED``) grouped by object
    and placement."""
    rows = [r for r in rows if r["status"] in MEASURED]
    placements: dict[str, set[str]] = {}
    for r in rows:
        placements.setdefault(r["object"], set()).add(r["placement"])
    out: dict[tuple[str, str], Group] = {}
    for r in rows:
        key = (r["object"], r["placement"])
        if key not in out:
            label = r["object"] if len(placements[r["object"]]) == 1 else f"{r['object']} @ {r['placement']}"
            out[key] = Group(label, r["object"], r["placement"], {})
        out[key].by_planner.setdefault(r["planner"], []).append(r)
    return list(out.values())


def figures(rows: Sequence[Row], column: str) -> list[float]:
    """The column's values of the rows that have one."""
    return [v for r in rows if (v := value(r, column)) is not None]


def dims(rows: Sequence[Row], axis: int) -> list[float]:
    """The rows' box dimension ``axis`` (0 L, 1 W, 2 H) [m], of those that have a box."""
    return [float(r["dims_m"].split()[axis]) for r in rows if r["dims_m"]]


def standard_error(values: Sequence[float]) -> float | None:
    """Standard error of the mean (``ddof=1``); None for fewer than two values."""
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else None


def mean_se(values: Sequence[float], digits: int, paper_figure: float | None = None) -> str:
    """``mean ± se`` (standard error of the mean, ``ddof=1``; no ``± se`` for one value), ``(paper)``
    after it where given; ``-`` for no values."""
    if not values:
        text = "-"
    else:
        text = f"{np.mean(values):.{digits}f}"
        if (se := standard_error(values)) is not None:
            text += f" ± {se:.{digits}f}"
    return text if paper_figure is None else f"{text} ({paper_figure:.{digits}f})"


def mann_whitney(a: Sequence[float], b: Sequence[float]) -> tuple[float, float] | None:
    """(U of ``a``, two-sided p) of two samples; None when either has fewer than two values (one against
    one gives p = 1 whichever is larger) or every value ties. p is exact for samples small enough
    (:data:`EXACT_SPLITS`)."""
    if len(a) < 2 or len(b) < 2 or len(set(a) | set(b)) == 1:
        return None
    splits = math.comb(len(a) + len(b), len(a))  # as many resamples as splits: scipy takes every one
    result = mannwhitneyu(a, b, alternative="two-sided",
                          method=PermutationMethod(n_resamples=splits) if splits <= EXACT_SPLITS
                          else "asymptotic")
    return float(result.statistic), float(result.pvalue)


def smallest_p(n_a: int, n_b: int) -> float:
    """The smallest two-sided p Mann-Whitney U can give for samples of ``n_a`` and ``n_b`` values (exact
    test, no ties: every value of one sample below every value of the other), 2 / C(n_a + n_b, n_a), at
    most 1: 0.333 for 2 against 2, 0.1 for 3 against 3, 0.029 for 4 against 4."""
    return min(1.0, 2.0 / math.comb(n_a + n_b, n_a))


def better(column: str) -> str:
    """``higher`` or ``lower``: which way a figure of the tables is better."""
    return "higher" if column in HIGHER_IS_BETTER else "lower"


def _directions(columns: Sequence[tuple[str, str, int]]) -> str:
    """The sentence saying which way each of ``columns`` (column, heading, decimals) is better."""
    parts = [f"{way} is better: " + ", ".join(f"`{h}`" for c, h, _ in columns if better(c) == way)
             for way in ("higher", "lower") if any(better(c) == way for c, _, _ in columns)]
    text = "; ".join(parts)
    return text[:1].upper() + text[1:] + "."


def _paper_figure(planner: str, column: str, obj: str) -> float | None:
    """Table I's figure of an object's row."""
    if column in ("coverage_pct", "chamfer_mm", "hausdorff_mm"):
        return paper.table_i(planner, column, obj)
    return None


def _paper_mean(planner: str, column: str) -> float | None:
    """The paper's mean over its objects (``PAPER_MEANS``) of a mean row."""
    return {"scan_time_s": paper.MEAN_SCAN_TIME_S, "path_m": paper.MEAN_PATH_M}.get(column, {}).get(planner)


def _table(header: Sequence[str], lines: Sequence[Sequence[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(line) + " |" for line in lines)]


def _mean_lines(gs: Sequence[Group]) -> list[list[str]]:
    """A line per planner of which the paper gives a mean over its objects: ``mean over N objects``, the
    scans of the planner (n) and, for each of ``PAPER_MEANS``, the mean ± se over the groups of their
    means (the paper's mean in brackets); the other cells empty."""
    lines = []
    for planner in dict.fromkeys(p for g in gs for p in g.by_planner):
        if all(_paper_mean(planner, c) is None for c in PAPER_MEANS):
            continue
        groups = [g for g in gs if g.by_planner.get(planner)]
        having = [g.by_planner[planner] for g in groups]
        cells = [mean_se([float(np.mean(v)) for rs in having if (v := figures(rs, c))], d,
                         _paper_mean(planner, c)) if c in PAPER_MEANS else ""
                 for c, _, d in RECONSTRUCTION]
        n_objects = len({g.object for g in groups})
        label = f"mean over {n_objects} object{'s' if n_objects > 1 else ''}"
        if len(groups) > n_objects:  # an object at several placements: each placement's mean counts
            label += f" at {len(groups)} placements"
        lines.append([label, planner, str(sum(len(rs) for rs in having)), cells[0], "", *cells[1:]])
    return lines


def reconstruction_table(gs: Sequence[Group], limits: Limits) -> list[str]:
    """Table I's layout: per group and planner, n and mean ± se (Table I's figure) of each reconstruction
    figure, the group's coverage limit beside its coverage; then the mean rows (:func:`_mean_lines`)."""
    header = ["object", "planner", "n", RECONSTRUCTION[0][1], "limit %",
              *(heading for _, heading, _ in RECONSTRUCTION[1:])]
    lines = []
    for g in gs:
        limit = limits.get((g.object, g.placement))
        for planner, rs in g.by_planner.items():
            cells = [mean_se(figures(rs, c), d, _paper_figure(planner, c, g.object))
                     for c, _, d in RECONSTRUCTION]
            lines.append([g.label, planner, str(len(rs)), cells[0], "-" if limit is None else f"{limit:.1f}",
                          *cells[1:]])
    return _table(header, lines + _mean_lines(gs))


def truth(rows: Sequence[Row]) -> list[float] | None:
    """The ground-truth L, W, H [m] of the rows' object (``dims_true_m``), None where none has it."""
    text = next((t for r in rows if (t := r.get("dims_true_m"))), None)
    return None if text is None else [float(v) for v in text.split()]


def _dims_line(values: Sequence[float] | None) -> str:
    return "-" if values is None else " x ".join(f"{v:.4f}" for v in values)


def _upper(rows: Sequence[Row]) -> list[float] | None:
    """The mean upper bound L, W, H [m] of the rows that have one (``dims_upper_m``), None without."""
    uppers = [[float(v) for v in t.split()] for r in rows if (t := r.get("dims_upper_m"))]
    return [float(v) for v in np.mean(uppers, axis=0)] if uppers else None


def _containers(rows: Sequence[Row]) -> str:
    """The containers chosen, each with how many scans chose it: ``medium (2), large (1)``; ``-``."""
    chosen = [c for r in rows if (c := r.get("container"))]
    return ", ".join(f"{name} ({chosen.count(name)})" for name in dict.fromkeys(chosen)) or "-"


def packing_table(gs: Sequence[Group]) -> list[str]:
    """The packing paper's Fig. 3 figures: per group and planner, mean ± se of L, W, H and the rest; then
    the ground-truth box (sim), the mean upper bound (the box the container is chosen for) and the
    containers chosen."""
    header = ["object", "planner", "n", *DIMS, *(heading for _, heading, _ in PACKING), "truth L x W x H m",
              "upper bound L x W x H m (mean)", "containers"]
    lines = [[g.label, planner, str(len(rs)), *(mean_se(dims(rs, k), 4) for k in range(3)),
              *(mean_se(figures(rs, c), d) for c, _, d in PACKING), _dims_line(truth(rs)),
              _dims_line(_upper(rs)), _containers(rs)]
             for g in gs for planner, rs in g.by_planner.items()]
    return _table(header, lines)


def _samples(rs: Sequence[Row], packing: bool) -> dict[str, list[float]]:
    """The rows' values of each tested figure: ``TESTED`` and, with ``packing``, ``PACKING_TESTED`` and the
    box dimensions (the packing paper tests the dimensions too)."""
    samples = {c: figures(rs, c) for c in TESTED}
    if packing:
        samples |= {**{c: figures(rs, c) for c in PACKING_TESTED},
                    **{name: dims(rs, k) for k, name in enumerate(DIMS)}}
    return samples


def tests_table(gs: Sequence[Group], packing: bool = True) -> tuple[list[str], list[tuple[int, int]]]:
    """Mann-Whitney U of every two planners of a group on each figure both have (the packing figures
    with ``packing``), with the smallest p the two sample sizes can give (:func:`smallest_p`); and the
    sample sizes (n A, n B) of the tests whose smallest p is not below ``SIGNIFICANCE`` (they cannot find
    a difference)."""
    lines = []
    too_small: list[tuple[int, int]] = []
    for g in gs:
        for (pa, ra), (pb, rb) in itertools.combinations(g.by_planner.items(), 2):
            samples_a, samples_b = _samples(ra, packing), _samples(rb, packing)
            for name, a in samples_a.items():
                if a and (b := samples_b[name]):
                    test = mann_whitney(a, b)
                    least = smallest_p(len(a), len(b))
                    if least >= SIGNIFICANCE:
                        too_small.append((len(a), len(b)))
                    lines.append([g.label, name, pa, pb, *(("-", "-") if test is None else
                                                           (f"{test[0]:.1f}", f"{test[1]:.4f}")),
                                  f"{least:.4f}"])
    return (_table(["object", "figure", "planner A", "planner B", "U (A)", "p", "smallest exact p"], lines),
            sorted(set(too_small)))


def _tests_note(too_small: Sequence[tuple[int, int]]) -> list[str]:
    """What the sample sizes of ``too_small`` mean for their tests, when there are any."""
    if not too_small:
        return []
    sizes = ", ".join(f"{a} against {b} ({smallest_p(a, b):.3f})" for a, b in too_small)
    return [f"With these numbers of scans the exact test cannot reach p < {SIGNIFICANCE:g} whatever the "
            f"values: the smallest p it can give is 2 / C(n A + n B, n A), for {sizes}. Such a test says "
            f"nothing about a difference (where values tie, `p` is the normal approximation's, no more "
            f"telling at these sizes); more seeds per planner can (4 against 4 can reach "
            f"{smallest_p(4, 4):.3f}).", ""]


def _panels(gs: Sequence[Group], rows: int, width: float, height: float) -> tuple[Figure, list[list[Axes]]]:
    """A figure with a column of ``rows`` panels for each group, at most ``GROUPS_PER_ROW`` columns side
    by side and further groups in bands below, each panel ``width`` x ``height`` [in]; the columns of
    panels in the groups' order."""
    columns = max(1, min(len(gs), GROUPS_PER_ROW))
    bands = -(-len(gs) // columns)
    fig = Figure(figsize=(width * columns, height * rows * bands))
    axes = fig.subplots(rows * bands, columns, squeeze=False)
    for slot in range(len(gs), bands * columns):  # the last band's empty places
        for r in range(rows):
            axes[(slot // columns) * rows + r, slot % columns].set_visible(False)
    return fig, [[axes[(i // columns) * rows + r, i % columns] for r in range(rows)] for i in range(len(gs))]


def planner_colours(gs: Sequence[Group]) -> dict[str, str]:
    """One colour per planner of the groups, in the order first met (matplotlib's ``C0``, ``C1``, ...),
    the same in every panel of both figures: a planner's place in one group's legend (another group may
    lack a planner whose scans all failed) must not give it another group's colour, nor may the bars
    under a legend take a colour of their own."""
    planners = dict.fromkeys(p for g in gs for p in g.by_planner)
    return {planner: f"C{n % 10}" for n, planner in enumerate(planners)}


def fig5_figure(gs: Sequence[Group], timelines: dict[RowId, Timeline]) -> Figure:
    """``fig5.png``: per group, Chamfer distance [mm] (top) and coverage [%] (bottom) against scan time
    [s], a dot where each scan ended and a curve per re-processed scan's timeline, each planner in its
    colour (:func:`planner_colours`), Table I's coverage dashed."""
    fig, panels = _panels(gs, 2, 4.0, 3.0)
    colours = planner_colours(gs)
    for g, (top, bottom) in zip(gs, panels, strict=True):
        for planner, rs in g.by_planner.items():
            colour = colours[planner]
            for ax, column in ((top, "chamfer_mm"), (bottom, "coverage_pct")):
                pairs = [(t, v) for r in rs if (t := value(r, "scan_time_s")) is not None
                         and (v := value(r, column)) is not None]
                ax.plot([t for t, _ in pairs], [v for _, v in pairs], "o", color=colour, label=planner)
                for r in rs:
                    if (timeline := timelines.get(row_id(r))) is not None:
                        ax.plot(np.array(timeline["t_s"], dtype=float),  # a missing figure (None): NaN
                                np.array(timeline[column], dtype=float), color=colour, linewidth=0.8)
            if (table_i := paper.table_i(planner, "coverage_pct", g.object)) is not None:
                bottom.axhline(table_i, color=colour, linestyle="--", linewidth=0.8)
        top.set_title(g.label)
        top.set_ylabel(f"Chamfer [mm], {better('chamfer_mm')} is better")
        bottom.set_ylabel(f"cloud coverage (eq. 13) [%],\n{better('coverage_pct')} is better")
        bottom.set_xlabel("scan time [s]")
        top.legend(fontsize="small")
    fig.tight_layout()
    return fig


def _save(fig: Figure, path: Path) -> None:
    """Save ``fig`` as ``path`` whole (a temporary file renamed over it)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)


def _means_and_errors(values: Sequence[Sequence[float]]) -> tuple[list[float], list[float] | None]:
    """Mean of each list (0 where one is empty) and their standard errors, None where no list has one
    (one value each: no error bar to draw)."""
    means = [float(np.mean(v)) if v else 0.0 for v in values]
    errors = [standard_error(v) or 0.0 for v in values]
    return means, errors if any(errors) else None


def fig3_figure(gs: Sequence[Group]) -> Figure:
    """``fig3.png``, the packing paper's Fig. 3 per group: the box dimensions L, W, H per planner, then
    each of ``PACKING``, as mean bars with standard errors; a figure's bars for the planners that have
    it, each planner's in its colour (:func:`planner_colours`), the one of the box panel's legend."""
    fig, panels = _panels(gs, len(PACKING) + 1, 3.5, 11.0 / (len(PACKING) + 1))
    colours = planner_colours(gs)
    for g, (box, *others) in zip(gs, panels, strict=True):
        planners = list(g.by_planner)
        width = 0.8 / len(planners)
        for n, planner in enumerate(planners):
            means, errors = _means_and_errors([dims(g.by_planner[planner], k) for k in range(3)])
            box.bar(np.arange(3) + n * width, means, width, yerr=errors, capsize=3, label=planner,
                    color=colours[planner])
        if (true_lwh := truth([r for rs in g.by_planner.values() for r in rs])) is not None:
            # the ground truth across each dimension's bars
            box.hlines(true_lwh, np.arange(3) - width / 2.0, np.arange(3) + width * (len(planners) - 0.5),
                       colors="black", linewidth=1.5, label="truth")
        box.set_xticks(np.arange(3) + width * (len(planners) - 1) / 2.0, ["L", "W", "H"])
        box.set_ylabel("box [m], best at the truth")
        # above the bars, which fill any corner of the panel on one object or another
        box.legend(fontsize="small", loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=len(planners) + 1,
                   frameon=False, borderaxespad=0.1)
        for ax, (column, heading, _) in zip(others, PACKING, strict=True):
            having = [p for p in planners if figures(g.by_planner[p], column)]
            means, errors = _means_and_errors([figures(g.by_planner[p], column) for p in having])
            ax.bar(having, means, yerr=errors, capsize=3, color=[colours[p] for p in having])
            ax.set_ylabel(f"{heading},\n{better(column)} is better")
        box.set_title(g.label, pad=20.0)
    fig.tight_layout()
    return fig


def _brackets(gs: Sequence[Group]) -> str:
    """What the brackets of the reconstruction table hold, when any cell has one: Table I's figure of an
    object and strategy it has, and in the mean rows the paper's mean over its objects for scan time and
    path; empty when none does (no object or planner of the grid is in the paper)."""
    pairs = [(planner, g.object) for g in gs for planner in g.by_planner]
    table_i = any(_paper_figure(p, c, o) is not None for p, o in pairs
                  for c in ("coverage_pct", "chamfer_mm", "hausdorff_mm"))
    means = any(_paper_mean(p, c) is not None for p, _ in pairs for c in PAPER_MEANS)
    held = (["Table I's in an object's row where it has the object and strategy"] if table_i else []) \
        + (["the paper's mean over its eight objects (section III-C) in a row `mean over N objects`, whose "
            "scan time and path are the mean of the objects' means (standard error across the objects)"]
           if means else [])
    return f"; in brackets the paper's figures: {' and '.join(held)}" if held else ""


def _millimetres(radius_m: float) -> str:
    return f"{radius_m * 1e3:g} mm"


def _coverage_words() -> str:
    """What ``coverage %`` and ``limit %`` are (the reconstruction table's sentence)."""
    return (f"`coverage %`: the visual-servoing paper's eq. 13, the share of the object's surface (eq. 13's "
            f"A: {N_GROUND_TRUTH_POINTS:,} points uniform on the mesh, faces pointing down left out) within "
            f"{_millimetres(COVERAGE_RADIUS_M)} of a point of the measured cloud (`unregistered coverage %`: "
            "the same before the mesh is registered to the cloud). `limit %`: the coverage limit, the share "
            "of that surface some reachable view can see (`cell eval limit`): a bound on where the views "
            "reach, not on how densely the sensor samples what it sees.")


def _surface_words(radii_m: Sequence[float]) -> str:
    """What ``surface reconstructed %`` is, its radius (``radii_m``: of the grid's cell files; none
    known: named by its setting), and why it differs from ``coverage %`` (the packing table's sentence)."""
    radius = " or ".join(_millimetres(r) for r in sorted(set(radii_m)))
    setting = "`packing.coverage_radius_m`, the occupancy map's resolution when unset"
    eq13 = _millimetres(COVERAGE_RADIUS_M)
    return (f"`surface reconstructed %`: the packing paper's surface coverage, the share of the same surface "
            f"sample within {f'{radius} ({setting})' if radius else setting} of the centre of a voxel of the "
            f"segmented object, where `coverage %` asks for a point of the cloud within {eq13}. On a sparse "
            f"cloud the two differ widely: an 8 x 8 time-of-flight sensor (the packing paper's) gives 64 "
            f"points a frame, centimetres apart at its range, so few surface points lie within {eq13} of "
            f"one, while the voxels they fill are within {radius or 'that radius'} of most of the surface.")


def _claims(gs: Sequence[Group]) -> list[str]:
    """The packing paper's claims on Fig. 3, when the grid has one of its objects scanned by one of its
    planners (else they are of nothing in the report)."""
    if not any(g.object in paper.PACKING_OBJECTS and any(p in paper.PACKING_PLANNERS for p in g.by_planner)
               for g in gs):
        return []
    return ["The paper gives Fig. 3 as plots only; its text claims:", "",
            *(f"- {claim}" for claim in paper.PACKING_CLAIMS), ""]


def unfinished_line(row: Row) -> str:
    """A scan that did not complete: ``<object> <placement> <planner> seed <seed>: <status>: <why>``."""
    return (f"{row['object']} {row['placement']} {row['planner']} seed {row['seed']}: {row['status']}: "
            f"{row['termination']}")


def _cut_short(rows: Sequence[Row]) -> list[str]:
    """The paragraph listing the scans in the figures that a limit of the job (its time budget) ended
    before their planner's own termination (``limit_reached``), when there are any: their figures are
    of a scan cut short, and a comparison of planners at a ``--max-time`` shorter than one of them needs
    is of how far each got, not of where each would have stopped."""
    cut = [r for r in rows if r["status"] in MEASURED and r.get("limit_reached") == "true"]
    if not cut:
        return []
    return [f"**Cut short**: {len(cut)} of the {sum(r['status'] in MEASURED for r in rows)} scans in the "
            "figures ended on a limit of the job (its time budget: `--max-time`, or the cell's "
            "`scan.max_time_s`), not on their planner's own termination; their figures are of a scan cut "
            "short (`limit_reached` in `results.csv`):", "",
            *(f"- {unfinished_line(r)}" for r in cut), ""]


def write_report(rows: Sequence[Row], out: Path, limits: Limits, title_lines: Sequence[str] = (),
                 timelines: dict[RowId, Timeline] | None = None, *, packing: bool = True,
                 packing_radii_m: Sequence[float] = ()) -> Path:
    """Write report.md and its figures into ``out``; ``limits`` the coverage limit [%] per object and
    placement (results.csv's texts; absent: not computed), ``timelines`` those of the re-processed
    scans by row (``cell.evaluation.grid.timelines``), ``packing`` whether it has the packing section
    (when the scans have its figures; else a line says results.csv holds them), ``packing_radii_m`` the
    radii [m] of ``surface reconstructed %`` of the grid's cell files. Returns report.md's path."""
    gs = groups(rows)
    statuses = sorted({r["status"] for r in rows})
    counts = ", ".join(f"{sum(r['status'] == s for r in rows)} {s}" for s in statuses)
    md = ["# Evaluation report", "", *title_lines, f"{len(rows)} scans: {counts}.", "", *_cut_short(rows)]
    if not gs:
        md += ["No scan ran to its end: no figures.", ""]
    else:
        md += ["## Reconstruction (visual-servoing paper, Table I layout)", "",
               f"{_coverage_words()} Mean ± standard error over the seeds{_brackets(gs)}. "
               f"{_directions(RECONSTRUCTION)}", "",
               *reconstruction_table(gs, limits), "",
               f"![coverage and Chamfer against scan time]({FIG5})", ""]
        _save(fig5_figure(gs, timelines or {}), out / FIG5)
        measured = any(r["iou"] for g in gs for rs in g.by_planner.values() for r in rs)
        if measured and not packing:
            md += ["The packing figures of these scans (the LR-NBV paper's Fig. 3: box, IoU, surface "
                   "reconstructed, poses) are not this report's; `results.csv` holds them.", ""]
        if measured and packing:
            md += ["## Packing (LR-NBV paper, Fig. 3)", "", *_claims(gs),
                   f"{_surface_words(packing_radii_m)} Mean ± standard error over the seeds. "
                   f"`L m`, `W m`, `H m`: the box measured, best at the truth (`truth`, the ground-truth box "
                   f"of the mesh: sim only; in `{FIG3}` a black mark). `upper bound`: the box grown by the "
                   f"sensor's error model, the one the container is chosen for (`containers`: how many "
                   f"scans chose each). {_directions(PACKING)}", "",
                   *packing_table(gs), "", f"![packing figures per planner]({FIG3})", ""]
            _save(fig3_figure(gs), out / FIG3)
        tests, too_small = tests_table(gs, packing)
        md += ["## Mann-Whitney U between planners", "", *tests, "", *_tests_note(too_small)]
    unfinished = [r for r in rows if r["status"] not in MEASURED]
    if unfinished:
        md += ["## Scans that did not complete (not in the figures above)", "",
               *(f"- {unfinished_line(r)}" for r in unfinished), ""]
    path = out / REPORT_MD
    write_text_atomic(path, "\n".join(md))
    return path

