"""Per-tick records in bounded memory (cell.control.decimation): the halving rule itself, and a servo job
whose per-tick series (telemetry, sensor path, tick periods) stay within the capacity while its outputs
still cover the whole job."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cell.control.decimation as decimation
from cell.config import load_config
from cell.control.decimation import DecimatedSeries
from cell.jobs.runner import ScanRequest, run_scan

from .conftest import FRANKA

BUDGET_S = 12.0  # the Franka cell's servo job: the primary task converges, then the secondary runs


def test_a_series_below_capacity_keeps_every_record() -> None:
    series: DecimatedSeries[int] = DecimatedSeries(capacity=8)
    for i in range(8):
        series.append(i)
    assert series.records() == list(range(8)) and series.count == 8 and series.stride == 1


@pytest.mark.parametrize("n", [9, 100, 1000, 12345])
def test_a_long_series_keeps_evenly_spaced_records_and_the_newest(n: int) -> None:
    capacity = 16
    series: DecimatedSeries[int] = DecimatedSeries(capacity=capacity)
    for i in range(n):
        series.append(i)
        assert len(series) <= capacity + 1  # at every point, not only at the end
    kept = series.records()
    stride = series.stride
    assert series.count == n and series.last == n - 1 and kept[-1] == n - 1
    assert kept[:-1] == list(range(0, n - 1, stride))[:len(kept) - 1]
    assert all(k % stride == 0 for k in kept[:-1])
    # every record offered has a kept one within one stride of it: the series covers the whole run
    assert np.max(np.diff(kept)) <= stride and len(kept) > capacity // 2


def test_an_empty_series_has_no_newest_record() -> None:
    series: DecimatedSeries[float] = DecimatedSeries()
    assert not series and series.records() == [] and len(series) == 0
    with pytest.raises(IndexError):
        _ = series.last


def test_a_servo_job_keeps_its_per_tick_series_within_the_capacity(tmp_path, monkeypatch) -> None:
    """With a capacity of 64, a 12 s VS-Local job at the cell's 100 Hz (1200 ticks) leaves a servo.csv of
    at most 65 rows spread over the whole job, the count of every tick and the exact longest one."""
    capacity = 64
    monkeypatch.setattr(decimation, "SERIES_CAPACITY", capacity)
    cfg = load_config(FRANKA)
    out = run_scan(ScanRequest(config=cfg, config_path=str(FRANKA), object="bunny", planner="vs-local",
                               out=tmp_path / "job", max_time_s=BUDGET_S)).folder
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "completed", result["termination"]
    control = result["control"]
    n_ticks = round(BUDGET_S * cfg.scan.control_rate_hz)
    assert abs(control["n_ticks"] - n_ticks) <= 2 and control["histogram"]["count"] == control["n_ticks"] - 1
    assert control["period_max_s"] == pytest.approx(1.0 / cfg.scan.control_rate_hz, rel=1e-3)  # sim clock
    rows = np.loadtxt(out / "servo.csv", delimiter=",", skiprows=1, usecols=0, ndmin=1)
    assert 2 <= len(rows) <= capacity + 1
    assert rows[-1] > BUDGET_S - 1.0 and np.all(np.diff(rows) > 0)  # up to the job's end, in order
    trajectory = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1)
    assert len(trajectory) >= control["n_ticks"]  # the per-tick record on disk is whole (a pose a tick)
