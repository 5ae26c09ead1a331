"""``cell eval``: the papers' experiments and any grid of scans as one command, with a report.

``vs-table``, ``packing`` and ``heldout`` are presets (``cell.evaluation.presets``) whose objects,
planners, placements, seeds and cell file the options override; ``grid`` takes them all from the options.
Every scan's job folder, ``results.csv``, ``report.md`` and its figures go under ``--out``; running the
same command again skips the scans already done. ``cell eval limit`` prints an object's coverage limit.
"""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.commands import command_group
from cell.cli.errors import err_console, fail, print_error
from cell.cli.object_scale import scale_of
from cell.cli.signals import interrupting
from cell.cli.values import parse_pose
from cell.config import load_config
from cell.evaluation import presets
from cell.evaluation.evaluate import evaluate
from cell.evaluation.executors import make_executor
from cell.evaluation.grid import WHOLE, Shard
from cell.evaluation.limit import DEFAULT_DIRECTIONS, cell_coverage_limit
from cell.evaluation.report import MEASURED, unfinished_line
from cell.evaluation.spec import load_placements
from cell.jobs.placement import check_placement
from cell.templates import template_path
from drivers.errors import CellError
from drivers.sim.objects import load_object

eval_app = command_group(help="Grids of scans (the papers' experiments, or any) with a report.",
                         no_args_is_help=True)
console = Console(soft_wrap=True)

Config = Annotated[Path | None, typer.Option(help="cell file (default: the shipped sim-franka-rgbd cell)")]
Placements = Annotated[Path | None, typer.Option(help="YAML list of [x_m, y_m, yaw_deg] placements")]
Out = Annotated[Path, typer.Option(help="output folder: job folders, results.csv, report.md, figures")]
ExecutorOpt = Annotated[str, typer.Option(help="local (a process pool) or ray")]
Jobs = Annotated[int | None, typer.Option(help="scans at a time (local default 2; ray: all the CPUs)")]
RayAddress = Annotated[str | None, typer.Option(help="Ray cluster address (default: a local instance)")]
MaxTime = Annotated[float | None, typer.Option(help="time budget of each scan [s] (default: the cell's)")]
Reprocess = Annotated[bool | None, typer.Option(
    "--reprocess/--online", help="measure each job's cloud re-processed at 1 mm as the paper's Table I, or "
                                 "the online cloud (default: vs-table re-processes, the others not)")]
Directions = Annotated[int, typer.Option(help="view directions per hemisphere of the coverage limit; 0: "
                                              "no coverage limit")]
ObjectScale = Annotated[float, typer.Option(help="multiplies the coordinates of every mesh file's object "
                                                "into metres (0.001 for meshes in millimetres); shipped "
                                                "objects are in metres and keep their size")]
ShardOpt = Annotated[str | None, typer.Option(help="I/N: run the I-th of N parts of the grid (the same "
                                                   "parts on every machine); each run rebuilds the report "
                                                   "from every finished scan in --out")]


def _run(preset_for: Callable[[Path], presets.Preset], config: Path | None, planners: list[str] | None,
         objects: list[str] | None, placements: Path | None, seeds: list[int] | None, out: Path,
         executor: str, jobs: int | None, ray_address: str | None, max_time: float | None,
         limit_directions: int, reprocess: bool | None, object_scale: float, shard: str | None) -> None:
    try:
        if limit_directions < 0:
            raise CellError(f"--limit-directions must be at least 1, or 0 for no coverage limit, got "
                            f"{limit_directions}")
        part = Shard.parse(shard) if shard is not None else WHOLE
        preset = preset_for(out)
        cfg = config if config is not None else preset.config
        load_config(cfg)  # a bad cell file fails here, naming the field, not in every worker
        # every scan checked as cell scan checks it, before any runs (check_specs)
        specs = preset.specs(cfg, objects, load_placements(placements) if placements else None, planners,
                             seeds, max_time, reprocess, object_scale)
        clouds = "the 1 mm re-processed clouds" if specs[0].reprocess else "the online clouds"
        pool = make_executor(executor, jobs, ray_address)
    except CellError as exc:
        raise fail(exc) from None
    with interrupting() as received:
        try:
            done = evaluate(specs, out, pool, limit_directions=limit_directions or None, shard=part,
                            packing=preset.packing_report,
                            title_lines=[f"Cell file: `{cfg}`; coverage, Chamfer and Hausdorff of {clouds}.",
                                         ""])
        except CellError as exc:
            raise fail(exc) from None
        except KeyboardInterrupt:
            why = signal.Signals(received[0]).name if received else "Ctrl-C"
            print_error(f"interrupted ({why}): the scans and coverage limits finished so far are kept in "
                        f"{out}; the same command resumes")
            raise typer.Exit(code=128 + (received[0] if received else signal.SIGINT)) from None
    console.print(f"report: {done.report}", markup=False, highlight=False)
    unfinished = [r for r in done.mine if r["status"] not in MEASURED]
    if unfinished:
        print_error(f"{len(unfinished)} of {len(done.mine)} scans did not complete:")
        for r in unfinished:
            err_console.print(f"  {unfinished_line(r)}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=1)


GRID_EXIT = ("\n\nEvery scan is checked as cell scan checks it before any runs. Exit code 0 when "
             "every scan of this run's part of the grid completed, 1 when one did not (each listed on "
             "standard error and in the report) or on bad input, 128 + the signal's number when "
             "interrupted (Ctrl-C, SIGTERM: the workers stop; the finished scans and limits are kept).")


@dataclass(frozen=True)
class GridDefaults:
    """What a grid command takes where an option is not given, in words for its ``--help``: a shared text
    ("default: sim-ur5e-tof for packing, sim-franka-rgbd for the others") read, under ``cell eval grid``,
    as if its packing planners got the ToF cell, which they do not."""

    config: str
    objects: str | None
    """None: the option is needed."""
    planners: str | None
    seeds: str


def _grid_command(name: str, preset_for: Callable[[Path], presets.Preset], doc: str,
                  defaults: GridDefaults) -> None:
    """Register ``cell eval <name>``: the grid of ``preset_for(out)`` with the options in its place, each
    option's help naming this command's own default (``defaults``)."""
    def command(out: Out, config: Path | None = None, planners: list[str] | None = None,
                objects: list[str] | None = None, placements: Placements = None,
                seeds: list[int] | None = None, executor: ExecutorOpt = "local",
                jobs: Jobs = None, ray_address: RayAddress = None, max_time: MaxTime = None,
                limit_directions: Directions = DEFAULT_DIRECTIONS, reprocess: Reprocess = None,
                object_scale: ObjectScale = 1.0, shard: ShardOpt = None) -> None:
        _run(preset_for, config, planners, objects, placements, seeds, out, executor, jobs, ray_address,
             max_time, limit_directions, reprocess, object_scale, shard)

    command.__doc__ = doc + GRID_EXIT
    # this command's own defaults in the help: set here, as objects (the annotations written above are
    # strings, ``from __future__ import annotations``, which typer resolves in the module's names only)
    command.__annotations__ |= {
        "config": Annotated[Path | None, typer.Option(help=f"cell file (default: {defaults.config})")],
        "planners": Annotated[list[str] | None, typer.Option(
            "--planners", help=f"planner names, repeat the option {_default(defaults.planners)}")],
        "objects": Annotated[list[str] | None, typer.Option(
            "--objects", help=f"shipped names or mesh files, repeat {_default(defaults.objects)}")],
        "seeds": Annotated[list[int] | None, typer.Option(
            "--seeds", help=f"job seeds, repeat the option (default: {defaults.seeds})")]}
    eval_app.command(name)(command)


def _default(text: str | None) -> str:
    return "(needed)" if text is None else f"(default: {text})"


def _words(values: Iterable[object]) -> str:
    return " ".join(str(v) for v in values)


def _preset_defaults(preset: presets.Preset, whose: str) -> GridDefaults:
    """A preset's defaults in words, its objects introduced as ``whose``."""
    objects = f"{whose}: {_words(o for o, _ in preset.cases)}"
    return GridDefaults(f"the shipped {preset.config.stem} cell", objects, _words(preset.planners),
                        _words(preset.seeds))


_grid_command("vs-table", lambda _: presets.VS_TABLE,
              "The visual-servoing paper's Table I: its eight objects x VS-Local / Global / Hybrid, seeds "
              "0 1 2, each job re-processed at 1 mm as the paper.",
              _preset_defaults(presets.VS_TABLE, "Table I's"))
_grid_command("packing", lambda _: presets.PACKING,
              "The LR-NBV paper's section 4: its four objects x LR-NBV / NBV / HEU, seeds 0 to 4.",
              _preset_defaults(presets.PACKING, "the paper's"))
_grid_command("heldout", lambda out: presets.heldout(out / "shapes"),
              "Fifteen shapes and placements that are not Table I's, VS-Local (shapes written to "
              "OUT/shapes); --objects cylinder runs one of them by name, where the suite places it.",
              GridDefaults("the shipped sim-franka-rgbd cell",
                           f"the suite's: {_words(o for o, _ in presets.HELDOUT_CASES)}", "vs-local", "0"))
_grid_command("grid", lambda _: presets.Preset(template_path("sim-franka-rgbd"), (), (), (0,)),
              "Any objects x placements (default the station's centre) x planners x seeds (default 0); "
              "--objects and --planners are needed.",
              GridDefaults("the shipped sim-franka-rgbd cell, whatever the planners: --config "
                           "config/sim-ur5e-tof.yaml for the packing paper's ToF cell", None, None, "0"))


@eval_app.command("limit")
def limit(object: Annotated[str, typer.Option("--object", help="shipped name or mesh file")],
          config: Config = None,
          placement: Annotated[str, typer.Option(help="x,y,yaw_deg from the station")] = "0,0,0",
          object_scale: Annotated[float, typer.Option(help="a mesh file's units to metres (not for "
                                                           "shipped objects, in metres)")] = 1.0,
          directions: Annotated[int, typer.Option(help="view directions per hemisphere (at least 1)")]
          = DEFAULT_DIRECTIONS,
          everywhere: Annotated[bool, typer.Option(help="count every view, reachable by the arm or not")]
          = False) -> None:
    """The object's coverage limit on the cell.

    The share of its surface (eq. 13's sample) that any reachable view (at any roll about its optical
    axis) within the sensor's range, field of view and grazing limit can see."""
    try:
        if directions < 1:  # before the cell file and the mesh are read
            raise CellError(f"--directions must be at least 1 (view directions per hemisphere), got "
                            f"{directions}")
        path = config if config is not None else template_path("sim-franka-rgbd")
        scale = scale_of(object, object_scale)
        cfg, mesh, pose = load_config(path), load_object(object, scale), parse_pose("--placement", placement)
        check_placement(cfg, mesh, pose, scale)  # as cell scan: a size it scans, on the table
        result = cell_coverage_limit(cfg, mesh, pose, directions, reachable=not everywhere)
    except CellError as exc:
        raise fail(exc) from None
    console.print(f"coverage limit: {result.coverage_pct:.2f} % of {result.n_points} surface points, from "
                  f"{result.n_reachable} reachable of {result.n_views} views", highlight=False)
