"""VL53L8CX link figures: the frame parser's throughput on a stream of 8x8 frames with garbage, and the
serial driver against the bridge emulator over a pseudo-terminal at 4x4 / 60 Hz (the sensor's fastest
mode): delivered frame rate and how long ``capture`` takes. Prints readable lines, then one line of JSON.

    .venv/bin/python benchmarks/vl53l8cx_link.py [--frames 3000] [--seconds 3]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from options import BenchmarkParser, count, positive

from drivers.depth.config import VL53L8CXConfig
from drivers.depth.vl53l8cx import protocol as p
from drivers.depth.vl53l8cx.emulator import SimToFSource, VL53L8CXEmulator
from drivers.depth.vl53l8cx.serial_driver import VL53L8CXSerial


def parser_throughput(n_frames: int) -> dict[str, float]:
    """Frames and megabytes per second the parser takes from ``n_frames`` 8x8 frames, each followed by
    20 bytes of garbage, fed in reads of 4 kB."""
    rng = np.random.default_rng(0)
    source = SimToFSource.fixed("cube", seed=0)
    z = source(8)
    frame = p.encode(p.RangingFrame(0, 0, 8, z.distance_mm, z.range_sigma_mm, z.target_status,
                                    z.reflectance_pct, z.nb_target_detected))
    junk = rng.integers(0, 256, 20, dtype=np.uint8).tobytes()
    stream = (frame + junk) * n_frames
    parser = p.FrameParser()
    t0 = time.perf_counter()
    for k in range(0, len(stream), 4096):  # reads of 4 kB, as from a serial port
        parser.feed(stream[k:k + 4096])
    dt = time.perf_counter() - t0
    assert parser.stats.frames == n_frames
    return {"parser_frames_per_s": round(n_frames / dt, 1),
            "parser_mb_per_s": round(len(stream) / dt / 1e6, 2)}


def pty_link(seconds: float) -> dict[str, float]:
    """Frame rate [Hz] the serial driver delivers from the emulator over a pseudo-terminal for ``seconds``
    [s], frames lost, and the median and p99 [ms] of how long ``capture`` waits."""
    emulator = VL53L8CXEmulator.on_pty(SimToFSource.fixed("cube", seed=1))
    sensor = VL53L8CXSerial(VL53L8CXConfig(type="vl53l8cx", port=emulator.url, resolution=4, frequency_hz=60))
    durations = []
    with emulator, sensor:
        sensor.capture()  # the first frame comes after the configuration round trip
        t_end = time.monotonic() + seconds
        n = 0
        t0 = time.monotonic()
        while time.monotonic() < t_end:
            t = time.perf_counter()
            sensor.capture()
            durations.append(time.perf_counter() - t)
            n += 1
        rate = n / (time.monotonic() - t0)
        lost = sensor.stats.lost
    d = np.asarray(durations) * 1e3
    return {"pty_rate_hz": round(rate, 2), "pty_frames_lost": lost,
            "capture_ms_median": round(float(np.median(d)), 2),
            "capture_ms_p99": round(float(np.percentile(d, 99)), 2)}


def main() -> None:
    parser = BenchmarkParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=count, default=3000, help="8x8 frames through the parser")
    parser.add_argument("--seconds", type=positive, default=3.0,
                        help="time the pseudo-terminal link runs [s]")
    args = parser.parse_args()
    figures = parser_throughput(args.frames) | pty_link(args.seconds)
    print(f"parser: {figures['parser_frames_per_s']:.0f} 8x8 frames/s ({figures['parser_mb_per_s']} MB/s)")
    print(f"pseudo-terminal link at 4x4 / 60 Hz: {figures['pty_rate_hz']} Hz delivered, "
          f"{figures['pty_frames_lost']} frames lost; capture waits {figures['capture_ms_median']} ms "
          f"median, {figures['capture_ms_p99']} ms p99 (mostly the wait for the next frame)")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
