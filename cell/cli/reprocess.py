"""``cell reprocess``: a job's cloud rebuilt offline at 1 mm (``cell.perception.reprocess``)."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from cell.cli.errors import fail
from cell.cli.jobs import coverage_line
from cell.cli.progress import stage_progress
from cell.jobs.rebuild import rebuild_result
from cell.perception.reprocess import reprocess_job
from drivers.errors import CellError

console = Console(soft_wrap=True)


def reprocess(job_dir: Path) -> None:
    """Rebuild a job's cloud offline at 1 mm with multiway registration (paper section III-B).

    A folder whose result.json is missing but whose frames are there gets its result.json back first
    (status interrupted). Progress: a bar on a terminal, else lines to standard error."""
    try:
        rebuilt = rebuild_result(job_dir)
        if rebuilt is not None:
            console.print(f"{job_dir / 'result.json'} was missing: rebuilt from {rebuilt['n_captures']} "
                          f"frames (status {rebuilt['status']})", markup=False, highlight=False)
        with stage_progress("reprocess") as show:
            out = reprocess_job(job_dir, progress=show)
    except CellError as exc:
        raise fail(exc) from None
    cov = out["metrics"]["coverage_pct"] if out.get("metrics") else None
    console.print(f"{out['n_frames']} frames, {out['n_cloud_points']} points at {out['voxel_m'] * 1e3:g} mm",
                  highlight=False)
    console.print(coverage_line(cov), highlight=False)
    console.print(f"wrote {job_dir / 'cloud_hires.ply'} and {job_dir / 'result_hires.json'}", markup=False,
                  highlight=False)
