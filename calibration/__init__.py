"""Calibration of the cell by the cell itself: the sensor mount (hand-eye), the table and the ToF zones;
every move goes through ``cell.jobs`` (and so the safety layer)."""

from importlib.resources import files
from pathlib import Path

CALIBRATIONS_FOLDER = "calibrations"
"""The folder of the data folder that keeps each calibration's views and result (``cell init`` makes it)."""
GUIDE_COMMAND = "cell calibrate guide"
"""The command that prints the calibration guide (this package's ``README.md``, shipped as package data):
what the cell file's ``# MEASURE:`` hints and ``cell init`` point to, as a cell's PC has no checkout."""


def guide_path() -> Path:
    """The installed calibration guide (``README.md`` beside this module)."""
    return Path(str(files(__name__).joinpath("README.md")))
