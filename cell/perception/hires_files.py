"""The names of what ``cell reprocess`` (``cell.perception.reprocess.reprocess_job``) writes into a job
folder, in a module of their own, without Open3D, so that the evaluation's reports can read them."""

from __future__ import annotations

CLOUD_HIRES_FILE = "cloud_hires.ply"
RESULT_HIRES_FILE = "result_hires.json"
HIRES_FILES = (CLOUD_HIRES_FILE, RESULT_HIRES_FILE)
"""What ``reprocess_job`` writes (the cloud, then the figures), in the job folder or its ``out_dir``."""
