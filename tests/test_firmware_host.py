"""The bridge firmware's protocol code, built on the host with g++ (``deploy/firmware/host/``), against the
real VL53L8CX serial driver over a pseudo-terminal: the configuration handshake, frames with the zones
the host build synthesises, clean link counters, and malformed, corrupted and refused commands answered
(or not) as ``docs/vl53l8cx-serial.md`` says. The sketch itself is type-checked against declaration-only
stand-ins of the Arduino core and ST's library, and the shared source as C++11 with a board's flags."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivers.depth.config import VL53L8CXConfig
from drivers.depth.vl53l8cx import protocol as p
from drivers.depth.vl53l8cx.serial_driver import VL53L8CXSerial
from drivers.errors import CellError, DriverError

FIRMWARE = Path(__file__).resolve().parent.parent / "deploy" / "firmware"
SKETCH = FIRMWARE / "vl53l8cx_bridge"
HOST = FIRMWARE / "host"
GXX = shutil.which("g++")
WARNINGS = ["-Wall", "-Wextra", "-Werror"]

pytestmark = pytest.mark.skipif(GXX is None,
                                reason="g++ is not installed (deploy/system-deps.sh installs it)")


def _gxx(*args: str | Path) -> None:
    assert GXX is not None
    done = subprocess.run([GXX, *map(str, args)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def bridge_host(tmp_path_factory: pytest.TempPathFactory) -> Path:
    exe = tmp_path_factory.mktemp("firmware") / "bridge_host"
    _gxx("-std=c++17", *WARNINGS, "-I", SKETCH, HOST / "bridge_host.cpp", SKETCH / "bridge_protocol.cpp",
         "-o", exe)
    return exe


def test_the_shared_source_builds_as_cxx11_with_a_boards_flags(tmp_path):
    _gxx("-std=c++11", "-pedantic", "-fno-exceptions", "-fno-rtti", *WARNINGS, "-c",
         SKETCH / "bridge_protocol.cpp", "-o", tmp_path / "bridge_protocol.o")


def test_the_sketch_type_checks_against_the_arduino_and_uld_declarations():
    _gxx("-std=c++11", "-fsyntax-only", *WARNINGS, "-I", HOST / "arduino_stubs", "-I", SKETCH, "-x", "c++",
         SKETCH / "vl53l8cx_bridge.ino")


@dataclass
class Bridge:
    """The host build serving the master side of a pseudo-terminal; ``port`` is the slave's name, and
    ``inject`` writes bytes to the bridge as if the host had sent them."""

    process: subprocess.Popen[str]
    port: str
    slave: int

    def inject(self, data: bytes) -> None:
        os.write(self.slave, data)

    def read_until(self, done: Callable[[p.Frame], bool]) -> tuple[bytes, list[p.Frame]]:
        """What the bridge sends, read on the slave side in the driver's place, up to the first frame for
        which ``done`` holds: the bytes and the frames decoded from them."""
        parser = p.FrameParser()
        data, frames = b"", []
        while not (frames and done(frames[-1])):
            chunk = os.read(self.slave, 4096)
            data += chunk
            frames += parser.feed(chunk)
        return data, frames

    def stop(self) -> dict[str, int]:
        """Stop it and return the counters it prints on exit."""
        self.process.send_signal(signal.SIGTERM)
        out, err = self.process.communicate(timeout=10)
        assert self.process.returncode == 0, err
        return {k: int(v) for k, v in (item.split("=") for item in out.split()[-5:])}


@pytest.fixture
def start_bridge(bridge_host: Path) -> Iterator:
    started: list[Bridge] = []

    def start(*flags: str) -> Bridge:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no translation, before the driver opens the port and does the same
        process = subprocess.Popen([str(bridge_host), *flags, str(master)], pass_fds=(master,),
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        os.close(master)
        assert process.stdout is not None and process.stdout.readline() == "ready\n"
        bridge = Bridge(process, os.ttyname(slave), slave)
        started.append(bridge)
        return bridge

    yield start
    for bridge in started:
        if bridge.process.poll() is None:
            bridge.process.kill()
            bridge.process.communicate()
        os.close(bridge.slave)


def _expected_zones(seq: int, resolution: int) -> dict[str, np.ndarray]:
    """The zones of the host build's measurement numbered ``seq`` (``UldMeasurement`` in bridge_host.cpp),
    first targets, in the protocol's order: the ULD's rows mirrored left to right, as the protocol document
    says, and the values the firmware sends for a zone with no target."""
    u = np.arange(resolution * resolution)
    empty = u % 7 == 6
    status = np.where(u % 5 == 4, 9, np.where((u % 5 == 0) & (u > 0), 4, 5))
    uld = {"distance_mm": np.where(empty, 0, 200 + 10 * u + seq % 50),
           "range_sigma_mm": np.where(empty, 0, 1 + u % 4),
           "target_status": np.where(empty, 255, status),
           "reflectance_pct": np.where(empty, 0, 10 + u % 80),
           "nb_target_detected": np.where(empty, 0, 2)}
    return {name: v.reshape(resolution, resolution)[:, ::-1].ravel() for name, v in uld.items()}


def _state(status: p.StatusFrame | None) -> tuple[int, int, bool, int, int]:
    assert status is not None
    return status.command, status.result, status.ranging, status.resolution, status.frequency_hz


def _capture_until(sensor: VL53L8CXSerial, done: Callable[[], bool], limit: int = 200) -> None:
    for _ in range(limit):
        sensor.capture()
        if done():
            return
    raise AssertionError("the condition never held")


@pytest.mark.parametrize("resolution, frequency", [(4, 60), (8, 15)])
def test_the_driver_configures_the_host_build_and_reads_its_frames(start_bridge, resolution, frequency):
    bridge = start_bridge()
    sensor = VL53L8CXSerial(VL53L8CXConfig(type="vl53l8cx", port=bridge.port, resolution=resolution,
                                           frequency_hz=frequency, timeout_s=2.0))
    with sensor:
        frames, raws = [], []
        for _ in range(8):
            frames.append(sensor.capture())
            raws.append(sensor.last_raw)
        stats = sensor.stats
        status = sensor.last_status
    # disconnect's STOP is answered: not ranging any more
    _, answers = bridge.read_until(lambda f: isinstance(f, p.StatusFrame) and f.command == p.CMD_STOP)
    assert answers[-1].result == p.RESULT_OK and not answers[-1].ranging
    counters = bridge.stop()
    # the handshake (STOP, SET_RESOLUTION, SET_FREQUENCY, START): START's answer came last, as configured
    assert _state(status) == (p.CMD_START, p.RESULT_OK, True, resolution, frequency)
    # connect's four commands and disconnect's STOP, nothing malformed
    assert counters == {"commands": 5, "crc_errors": 0, "bad_headers": 0, "malformed": 0,
                        "bytes_discarded": 0}
    for frame, raw in zip(frames, raws, strict=True):
        assert raw.resolution == resolution
        for name, values in _expected_zones(raw.seq, resolution).items():
            np.testing.assert_array_equal(getattr(raw, name), values, err_msg=name)
        valid = np.isin(raw.target_status, (5, 9)) & (raw.nb_target_detected > 0)
        np.testing.assert_allclose(np.linalg.norm(frame.points, axis=1), raw.distance_mm[valid] / 1000.0)
    assert (stats.crc_errors, stats.bad_headers, stats.malformed, stats.bytes_discarded) == (0, 0, 0, 0)
    assert (stats.gaps, stats.lost, stats.duplicates, stats.restarts) == (0, 0, 0, 0)
    assert stats.ranging_frames >= len(frames)


def _bad_command_frames() -> tuple[list[bytes], dict[str, int]]:
    """Host frames that are not commands, and what the bridge's receiver must count for them."""
    flipped = bytearray(p.command(100, 0, p.CMD_SET_RESOLUTION, 8))
    flipped[-1] ^= 0x40
    other_version = bytearray(p.command(101, 0, p.CMD_QUERY))
    other_version[2] = 2
    too_long = p.frame_bytes(p.TEXT, 102, 0, b"longer than commands")  # more than the bridge buffers
    wrong_length = p.frame_bytes(p.CMD_SET_RESOLUTION, 103, 0, bytes([8, 8]))  # good CRC, a byte too many
    # A header whose length (16) swallows the QUERY behind it: only moving on by one byte after its CRC
    # error finds the QUERY again.
    swallowing = p.command(104, 0, p.CMD_STOP)[:p.HEADER_SIZE]
    swallowing = swallowing[:4] + (16).to_bytes(2, "little") + swallowing[6:]
    query = p.command(105, 0, p.CMD_QUERY)
    rest = bytes(p.HEADER_SIZE + 16 + p.CRC_SIZE - len(swallowing) - len(query))  # the rest of its length
    frames = [bytes(flipped), bytes(other_version), too_long, wrong_length, swallowing, query, rest]
    assert b"".join(frames).count(p.MAGIC) == 6  # one magic per frame: what is discarded is known exactly
    return frames, {"crc_errors": 2, "bad_headers": 2, "malformed": 1,
                    "bytes_discarded": sum(map(len, (flipped, other_version, too_long, swallowing, rest)))}


def test_bad_commands_are_dropped_or_refused_as_the_protocol_says(start_bridge):
    bridge = start_bridge()
    sensor = VL53L8CXSerial(VL53L8CXConfig(type="vl53l8cx", port=bridge.port, resolution=4, frequency_hz=60,
                                           timeout_s=2.0))
    sensor.connect()
    frames, expected = _bad_command_frames()
    # None of them is a command: no answer, no change; the QUERY among them is answered.
    bridge.inject(b"".join(frames))
    _capture_until(sensor, lambda: sensor.last_status.command == p.CMD_QUERY)
    assert _state(sensor.last_status) == (p.CMD_QUERY, p.RESULT_OK, True, 4, 60)
    # 8x8 while at 60 Hz: the frequency comes down to the sensor's 15 Hz, and the frames are 8x8
    bridge.inject(p.command(106, 0, p.CMD_SET_RESOLUTION, 8))
    _capture_until(sensor, lambda: sensor.last_raw.resolution == 8)
    assert _state(sensor.last_status) == (p.CMD_SET_RESOLUTION, p.RESULT_OK, True, 8, 15)
    # 16 Hz is more than the sensor does at 8x8: refused with 'invalid parameter', nothing changes, and
    # the driver faults on the refusal.
    bridge.inject(p.command(107, 0, p.CMD_SET_FREQUENCY, 16))
    with pytest.raises(DriverError, match=r"answered command 0x84 with 'invalid parameter'") as refused:
        _capture_until(sensor, lambda: False)
    assert isinstance(refused.value, CellError)
    assert _state(sensor.last_status) == (p.CMD_SET_FREQUENCY, p.RESULT_INVALID_PARAMETER, True, 8, 15)
    stats = sensor.stats
    sensor.disconnect()
    counters = bridge.stop()
    assert (stats.crc_errors, stats.malformed, stats.gaps, stats.lost) == (0, 0, 0, 0)
    # the four of the handshake, QUERY, SET_RESOLUTION and the refused SET_FREQUENCY
    assert counters == {"commands": 7, **expected}


def test_without_a_sensor_every_command_fails_with_the_boards_message(start_bridge):
    bridge = start_bridge("--sensor-missing")
    sensor = VL53L8CXSerial(VL53L8CXConfig(type="vl53l8cx", port=bridge.port, resolution=8, frequency_hz=15,
                                           timeout_s=2.0))
    sensor.connect()
    with pytest.raises(DriverError, match=r"answered command 0x82 with 'sensor error' \(last message: "
                                          r"VL53L8CX not initialised"):
        sensor.capture()
    sensor.disconnect()
    bridge.stop()


def test_the_host_build_refuses_a_bad_command_line(bridge_host):
    for args in ([], ["x"], ["3", "4"]):
        done = subprocess.run([str(bridge_host), *args], capture_output=True, text=True, timeout=10)
        assert done.returncode == 2 and "usage" in done.stderr


def test_the_first_frames_are_the_bytes_the_python_encoder_makes(start_bridge):
    """Read raw in the driver's place: the banner, then the unsolicited STATUS (command 0, ok, not ranging,
    8x8 at 15 Hz), numbered 0 and 1, byte for byte what ``protocol.encode`` makes of them."""
    bridge = start_bridge()
    data, frames = bridge.read_until(lambda f: isinstance(f, p.StatusFrame))
    banner, status = frames
    assert isinstance(banner, p.TextFrame) and banner.seq == 0 and "protocol 1" in banner.text
    assert status == p.StatusFrame(1, status.timestamp_us, 0, p.RESULT_OK, False, 8, 15)
    assert data == p.encode(banner) + p.encode(status)
    bridge.stop()
