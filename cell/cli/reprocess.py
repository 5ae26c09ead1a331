"""``cell reprocess``: a job's cloud rebuilt offline at 1 mm (``cell.perception.reprocess``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cell.cli.errors import fail, print_warning
from cell.cli.jobs import coverage_line
from cell.cli.progress import stage_progress
from cell.config import load_config
from cell.jobs.rebuild import (
    check_job_dir,
    job_cell_file,
    output_folder,
    rebuild_result,
    recorded_result,
    remove_live_cloud,
)
from cell.jobs.recorder import RESULT_FILE
from cell.perception.hires_files import HIRES_FILES
from cell.perception.reprocess import reprocess_job
from drivers.atomic_file import check_writable
from drivers.errors import CellError

console = Console(soft_wrap=True)


def _writable(folder: Path) -> bool:
    try:
        check_writable(folder)
    except OSError:
        return False
    return True


def reprocess(
    job_dir: Annotated[Path, typer.Argument(metavar="JOB_DIR", help="the job folder")],
    out: Annotated[Path | None, typer.Option(help=f"folder to write {' and '.join(HIRES_FILES)} to, made if "
                                                  "missing (default: the job folder)")] = None,
    config: Annotated[Path | None, typer.Option(help="the cell file the job ran with (default: the one the "
                                                     "job names)")] = None,
) -> None:
    """Rebuild a job's cloud offline at 1 mm with multiway registration (paper section III-B).

    A folder whose result.json is missing or unreadable but whose frames are there gets its result.json
    back first (status interrupted; an unreadable one is kept as result.json.unreadable); a frame that
    cannot be read is skipped with a warning. A read-only job folder is refused before any work: give
    --out. The crop box is that of the cell file the job names (relative to the job folder, as the
    service names its copy); when that is not found (a folder copied off the cell), the job is refused:
    give its cell file with --config. Progress: a bar on a terminal, else lines to standard error."""
    try:
        check_job_dir(job_dir)
        target = output_folder(job_dir, out, HIRES_FILES)
        recorded = recorded_result(job_dir)
        cell_file = job_cell_file(job_dir, recorded.result, config)
        crop = load_config(cell_file).perception.crop_box
        if recorded.problem is not None:
            # output_folder found the job folder writable when it is where the outputs go
            if target == job_dir or _writable(job_dir):
                kept = rebuild_result(job_dir, recorded)
                aside = f"; the unreadable file is kept as {kept}" if kept is not None else ""
                console.print(f"{job_dir / RESULT_FILE} was {recorded.problem}: rebuilt from "
                              f"{recorded.result['n_captures']} frames (status {recorded.result['status']})"
                              f"{aside}", markup=False, highlight=False)
            else:  # a read-only job folder, the outputs going to --out (output_folder refused it without)
                print_warning(f"{job_dir / RESULT_FILE} is {recorded.problem} and the job folder is "
                              "read-only: re-processing with a result rebuilt from job.json and the frames, "
                              "not written")
        with stage_progress("reprocess") as show:
            outcome = reprocess_job(job_dir, crop=crop, crop_source=str(cell_file), progress=show,
                                    out_dir=target, result=recorded.result)
    except CellError as exc:
        raise fail(exc) from None
    for skipped in outcome["skipped_frames"]:
        print_warning(f"skipped {skipped['reason']}")
    if remove_live_cloud(job_dir):
        console.print("removed the live cloud snapshot cloud_live.npy the job left behind", highlight=False)
    cov = outcome["metrics"]["coverage_pct"] if outcome.get("metrics") else None
    n_skipped = len(outcome["skipped_frames"])
    skipped_text = f" ({n_skipped} unreadable frames skipped)" if n_skipped else ""
    console.print(f"{outcome['n_frames']} frames{skipped_text}, {outcome['n_cloud_points']} points at "
                  f"{outcome['voxel_m'] * 1e3:g} mm", highlight=False, markup=False)
    console.print(coverage_line(cov), highlight=False)
    console.print(f"wrote {' and '.join(str(target / name) for name in HIRES_FILES)}", markup=False,
                  highlight=False)
