"""``cell doctor``: what a commissioning engineer checks on a cell's PC before the first scan, each check
a :class:`Finding` (ok, warn or fail, with the fix in one line).

:mod:`cell.doctor.machine` looks at this computer (Python, packages, kernels, libraries, clock, CPU
governor, real-time limits, disk, ports); :mod:`cell.doctor.devices` at what the cell file names (the
serial port, the robot's controller); :func:`cell.doctor.report.run_checks` runs them all.
"""
