"""Calibration of the cell by the cell itself: the sensor mount (hand-eye), the table and the ToF zones;
every move goes through ``cell.jobs`` (and so the safety layer)."""

CALIBRATIONS_FOLDER = "calibrations"
"""The folder of the data folder that keeps each calibration's views and result (``cell init`` makes it)."""
