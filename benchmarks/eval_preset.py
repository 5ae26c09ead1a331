"""A helper module of the benchmarks, not a benchmark (running it does nothing): what the ones that judge
a preset of ``cell eval`` share: run it as a user does (the ``cell`` console script beside this Python, so
the benchmark measures the product), then read its results.csv."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from options import BenchmarkParser

from cell.evaluation.grid import RESULTS_CSV
from cell.evaluation.report import REPORT_MD
from cell.evaluation.results import Row, read_csv


def preset_parser(description: str, command: str, note: str = "") -> argparse.ArgumentParser:
    """A benchmark's parser whose help ends with the options it passes on to ``cell eval <command>``, read
    from that command (so that the help shows what the benchmark accepts), ``note`` after their heading."""
    import typer.core
    import typer.main

    from cell.cli.eval import eval_app

    group = typer.main.get_command(eval_app)
    assert isinstance(group, typer.core.TyperGroup)
    lines = [f"other options go to `cell eval {command}` as they are{note}:"]
    for param in group.commands[command].params:
        if isinstance(param, typer.core.TyperOption) and param.name != "out":
            lines.append(f"  {', '.join([*param.opts, *param.secondary_opts])}: {param.help}")
    return BenchmarkParser(description=description, epilog="\n".join(lines),
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def run_preset(preset: str, default_out: Path, description: str) -> tuple[Path, list[Row]]:
    """``cell eval <preset> --out OUT`` with the script's other options passed on; exits with its exit
    code when it fails, unless it wrote its report (exit code 1: some scans did not complete, which
    the report lists and leaves out of its figures). Returns report.md's path and results.csv's rows."""
    parser = preset_parser(description, preset)
    parser.add_argument("--out", type=Path, default=default_out, help="the evaluation's output folder")
    args, rest = parser.parse_known_args()
    cell = Path(sys.executable).with_name("cell")
    report = args.out / REPORT_MD
    start = time.time()
    done = subprocess.run([str(cell), "eval", preset, "--out", str(args.out), *rest], check=False)
    wrote_report = report.is_file() and report.stat().st_mtime >= start
    if done.returncode and not (done.returncode == 1 and wrote_report):
        sys.exit(done.returncode)
    return report, read_csv(args.out / RESULTS_CSV)
