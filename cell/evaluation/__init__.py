"""Grids of scan jobs (objects x placements x planners x seeds), run on a local process pool or on Ray,
resumable, and the report of their results (``cell eval``).

Layering: above ``cell.jobs`` (each scan is a ``run_scan`` job), below ``cell.service`` and the CLI.
"""
