"""``cell eval``: the papers' experiments and any grid of scans as one command, with a report.

``vs-table``, ``packing`` and ``heldout`` are presets (``cell.evaluation.presets``) whose objects,
planners, placements, seeds and cell file the options override; ``grid`` takes them all from the options.
Every scan's job folder, ``results.csv``, ``report.md`` and its figures go under ``--out``; running the
same command again skips the scans already done. ``cell eval limit`` prints an object's coverage limit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.errors import fail
from cell.config import load_config
from cell.evaluation import presets
from cell.evaluation.evaluate import evaluate
from cell.evaluation.executors import make_executor
from cell.evaluation.limit import DEFAULT_DIRECTIONS, cell_coverage_limit
from cell.evaluation.spec import cross, load_placements, parse_placement
from cell.templates import template_path
from drivers.errors import CellError
from drivers.sim.objects import load_object

eval_app = typer.Typer(help="Grids of scans (the papers' experiments, or any) with a report.",
                       no_args_is_help=True)
console = Console(soft_wrap=True)

Config = Annotated[Path | None, typer.Option(help="cell file (default: the preset's shipped sim cell)")]
Planners = Annotated[list[str] | None, typer.Option("--planners", help="planner names (repeat the option)")]
Objects = Annotated[list[str] | None, typer.Option("--objects", help="shipped names or mesh files (repeat)")]
Placements = Annotated[Path | None, typer.Option(help="YAML list of [x_m, y_m, yaw_deg] placements")]
Seeds = Annotated[list[int] | None, typer.Option("--seeds", help="job seeds (repeat the option)")]
Out = Annotated[Path, typer.Option(help="output folder: job folders, results.csv, report.md, figures")]
ExecutorOpt = Annotated[str, typer.Option(help="local (a process pool) or ray")]
Jobs = Annotated[int | None, typer.Option(help="scans at a time (local default 2; ray: all the CPUs)")]
RayAddress = Annotated[str | None, typer.Option(help="Ray cluster address (default: a local instance)")]
MaxTime = Annotated[float | None, typer.Option(help="time budget of each scan [s] (default: the cell's)")]
Directions = Annotated[int, typer.Option(help="view directions per hemisphere of the coverage limit; 0: "
                                              "no coverage limit")]


def _run(preset: presets.Preset, config: Path | None, planners: list[str] | None, objects: list[str] | None,
         placements: Path | None, seeds: list[int] | None, out: Path, executor: str, jobs: int | None,
         ray_address: str | None, max_time: float | None, limit_directions: int) -> None:
    try:
        cfg = config if config is not None else preset.config
        load_config(cfg)  # a bad cell file fails here, naming the field, not in every worker
        if objects or placements:
            where = (load_placements(placements) if placements
                     else list(dict.fromkeys(p for _, p in preset.cases)) or [presets.CENTRE])
            what = objects or list(dict.fromkeys(o for o, _ in preset.cases))
            cases = presets.crossed(what, where)
        else:
            cases = preset.cases
        specs = cross(str(cfg.resolve()), cases, planners or preset.planners, seeds or preset.seeds, max_time)
        if not specs:
            raise CellError("the grid is empty: give --objects and --planners")
        report = evaluate(specs, out, make_executor(executor, jobs, ray_address),
                          limit_directions=limit_directions or None,
                          title_lines=[f"Cell file: `{cfg}`; executor: {executor}.", ""])
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"report: {report}", markup=False, highlight=False)


@eval_app.command("vs-table")
def vs_table(out: Out, config: Config = None, planners: Planners = None, objects: Objects = None,
             placements: Placements = None, seeds: Seeds = None, executor: ExecutorOpt = "local",
             jobs: Jobs = None, ray_address: RayAddress = None, max_time: MaxTime = None,
             limit_directions: Directions = DEFAULT_DIRECTIONS) -> None:
    """The visual-servoing paper's Table I: its eight objects x VS-Local / Global / Hybrid, seeds 0 1 2."""
    _run(presets.VS_TABLE, config, planners, objects, placements, seeds, out, executor, jobs, ray_address,
         max_time, limit_directions)


@eval_app.command("packing")
def packing(out: Out, config: Config = None, planners: Planners = None, objects: Objects = None,
            placements: Placements = None, seeds: Seeds = None, executor: ExecutorOpt = "local",
            jobs: Jobs = None, ray_address: RayAddress = None, max_time: MaxTime = None,
            limit_directions: Directions = DEFAULT_DIRECTIONS) -> None:
    """The LR-NBV paper's section 4: its four objects x LR-NBV / NBV / HEU, seeds 0 to 4."""
    _run(presets.PACKING, config, planners, objects, placements, seeds, out, executor, jobs, ray_address,
         max_time, limit_directions)


@eval_app.command("heldout")
def heldout(out: Out, config: Config = None, planners: Planners = None, objects: Objects = None,
            placements: Placements = None, seeds: Seeds = None, executor: ExecutorOpt = "local",
            jobs: Jobs = None, ray_address: RayAddress = None, max_time: MaxTime = None,
            limit_directions: Directions = DEFAULT_DIRECTIONS) -> None:
    """Ten shapes and placements that are not Table I's, VS-Local (shapes written to OUT/shapes)."""
    try:
        preset = presets.heldout(out / "shapes")
    except OSError as exc:
        raise fail(f"cannot write the held-out shapes: {exc}") from None
    _run(preset, config, planners, objects, placements, seeds, out, executor, jobs, ray_address, max_time,
         limit_directions)


@eval_app.command("grid")
def grid(out: Out, objects: Objects = None, planners: Planners = None, config: Config = None,
         placements: Placements = None, seeds: Seeds = None, executor: ExecutorOpt = "local",
         jobs: Jobs = None, ray_address: RayAddress = None, max_time: MaxTime = None,
         limit_directions: Directions = DEFAULT_DIRECTIONS) -> None:
    """Any objects x placements (default the station's centre) x planners x seeds (default 0)."""
    if not objects or not planners:
        raise fail("grid needs --objects and --planners", code=2)
    preset = presets.Preset(template_path("sim-franka-rgbd"), (), (), (0,))
    _run(preset, config, planners, objects, placements, seeds, out, executor, jobs, ray_address, max_time,
         limit_directions)


@eval_app.command("limit")
def limit(object: Annotated[str, typer.Option("--object", help="shipped name or mesh file")],
          config: Config = None,
          placement: Annotated[str, typer.Option(help="x,y,yaw_deg from the station")] = "0,0,0",
          object_scale: Annotated[float, typer.Option(help="mesh units to metres")] = 1.0,
          directions: Annotated[int, typer.Option(help="view directions per hemisphere")]
          = DEFAULT_DIRECTIONS,
          everywhere: Annotated[bool, typer.Option(help="count every view, reachable by the arm or not")]
          = False) -> None:
    """The object's coverage limit on the cell: the share of its surface (eq. 13's sample) that any
    reachable view within the sensor's range, field of view and grazing limit can see."""
    try:
        path = config if config is not None else template_path("sim-franka-rgbd")
        result = cell_coverage_limit(load_config(path), load_object(object, object_scale),
                                     parse_placement(placement), directions, reachable=not everywhere)
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"coverage limit: {result.coverage_pct:.2f} % of {result.n_points} surface points, from "
                  f"{result.n_reachable} reachable of {result.n_views} views", highlight=False)
