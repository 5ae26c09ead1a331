"""``vl53l8cx`` over a serial link: a bridge board speaking the frame format of ``docs/vl53l8cx-serial.md``.

The port is a pyserial URL (``/dev/ttyACM0``, ``socket://127.0.0.1:5555``, ``loop://``, ...). ``connect``
opens it and sends STOP, SET_RESOLUTION, SET_FREQUENCY and START; the driver does not wait for the
bridge's STATUS answers (a stream without them is still read), but a STATUS that reports a failure
faults the driver. From ``connect`` to ``disconnect`` a reader thread keeps the port drained: it decodes
what arrives and stamps each RANGING frame with the clock when it arrives. ``capture`` returns the newest
RANGING frame not returned yet, waiting up to ``timeout_s`` for one.

Why a reader: a port nobody reads fills up (the host's tty buffer, then the bridge's own), and the bridge
sends what it had queued once it is read again. A frame read only when a capture asks could then be a
second or more old, taken while the arm moved, yet arrive after the capture asked for a frame of the
arm at rest. Drained all along, a frame's arrival is its measurement's time to within the link's latency.

Faults (``capture`` raises ``DriverError`` until the next ``connect``): no RANGING frame for ``timeout_s``
(a silent port), a read or write error (a vanished port: unplugged board, closed socket or pseudo-
terminal), a STATUS with a failure result. Garbage and corrupted frames are not faults: the parser
resynchronises on the next magic and ``stats`` counts them, with the device's sequence gaps.

pyserial is an optional dependency (the ``tof`` extra), imported when connecting.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from drivers.clock import Clock, WallClock
from drivers.depth.base import DepthFrame, DepthSensor, SensorModel
from drivers.depth.config import VL53L8CXConfig
from drivers.depth.vl53l8cx import protocol as p
from drivers.depth.vl53l8cx.frames import configured_correction, depth_frame, sensor_model
from drivers.errors import DeviceFault, DriverError
from drivers.scheduling import ordinary_scheduling

READ_SLICE_S = 0.02
"""Longest single blocking read of the reader thread [s], so that it sees a disconnect that soon."""
READER_JOIN_S = 1.0

INSTALL_HINT = "pyserial is not installed; install it with: pip install 'cell[tof]' (or pip install pyserial)"


@dataclass(frozen=True)
class LinkStats:
    """Counters of a serial link since ``connect``: ``bytes_read`` from the port and decoded (all of them
    when the reader has caught up with the port); decoded ``frames`` and ``ranging_frames``, of which
    ``skipped`` were never returned because a newer one had arrived by the next ``capture``; the parser's
    ``crc_errors``, ``bad_headers``, ``malformed`` frames and ``bytes_discarded``; the device's sequence
    ``gaps`` (jumps), ``lost`` frames (numbers skipped), ``duplicates`` and ``restarts``."""

    bytes_read: int
    frames: int
    ranging_frames: int
    skipped: int
    crc_errors: int
    bad_headers: int
    malformed: int
    bytes_discarded: int
    gaps: int
    lost: int
    duplicates: int
    restarts: int


def import_serial() -> Any:
    """The ``serial`` module, or a ``DriverError`` naming the package that provides it."""
    try:
        import serial
    except ImportError:
        raise DriverError(INSTALL_HINT, device="depth vl53l8cx") from None
    return serial


class VL53L8CXSerial(DepthSensor):
    """A VL53L8CX behind a serial bridge (see the module docstring). ``clock`` stamps frames (the job's
    clock; the wall clock by default). After a frame, ``last_raw`` holds its device-side form."""

    name = "vl53l8cx"

    def __init__(self, config: VL53L8CXConfig, clock: Clock | None = None) -> None:
        if config.port is None:
            raise DriverError("the serial backend needs sensor.port (a pyserial URL)", device=self.device)
        self.config = config
        self.port_url: str = config.port
        self._correction = configured_correction(config)
        self._clock = clock if clock is not None else WallClock()
        self._serial: Any = None
        self._parser = p.FrameParser()
        self._sequence = p.SequenceCounter()
        # the reader thread's and capture's shared state: the frames not returned yet with their arrival
        # times, the fault, the counters
        self._cond = threading.Condition()
        self._pending: deque[tuple[float, p.RangingFrame]] = deque()
        self._fault: str | None = None
        self._reader: threading.Thread | None = None
        self._stop_reading = threading.Event()
        self._bytes_read = 0
        self._ranging_frames = 0
        self._skipped = 0
        self._host_seq = 0
        self._seq = 0
        self.last_raw: p.RangingFrame | None = None
        self.last_status: p.StatusFrame | None = None
        self._at_last_frame: tuple[int, int, p.StatusFrame | None] = (0, 0, None)
        self.messages: deque[str] = deque(maxlen=20)

    @property
    def device(self) -> str:
        return f"depth vl53l8cx at {self.config.port}"

    # -- connection ------------------------------------------------------------------------------------
    def connect(self) -> None:
        serial = import_serial()
        self.disconnect()
        self._parser = p.FrameParser()
        self._sequence = p.SequenceCounter()
        self._pending.clear()
        self._fault = None
        self._bytes_read = 0
        self._ranging_frames = 0
        self._skipped = 0
        self._at_last_frame = (0, 0, self.last_status)
        try:
            self._serial = serial.serial_for_url(self.port_url, baudrate=self.config.baudrate,
                                                 timeout=READ_SLICE_S, write_timeout=self.config.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"cannot open the port: {exc}", device=self.device) from None
        c = self.config
        for cmd, value in ((p.CMD_STOP, None), (p.CMD_SET_RESOLUTION, c.resolution),
                           (p.CMD_SET_FREQUENCY, c.frequency_hz), (p.CMD_START, None)):
            self._send(cmd, value)
        self._stop_reading.clear()
        self._reader = threading.Thread(target=self._read_loop, name="vl53l8cx reader", daemon=True)
        self._reader.start()

    def disconnect(self) -> None:
        """Ask the bridge to stop ranging (best effort: the port may be gone) and close the port."""
        if self._serial is None:
            return
        self._stop_reading.set()
        if self._reader is not None:
            self._reader.join(READER_JOIN_S)
            self._reader = None
        port, self._serial = self._serial, None
        if self._fault is None:
            serial = import_serial()
            # closing anyway: a port that has gone has nothing left to stop
            with contextlib.suppress(serial.SerialException, OSError):
                port.write(p.command(self._host_seq, self._now_us(), p.CMD_STOP))
                port.flush()
        port.close()

    @property
    def is_connected(self) -> bool:
        return self._serial is not None and self._fault is None

    @property
    def model(self) -> SensorModel:
        return sensor_model(self.config)

    @property
    def stats(self) -> LinkStats:
        with self._cond:
            s, q = self._parser.stats, self._sequence
            return LinkStats(bytes_read=self._bytes_read, frames=s.frames,
                             ranging_frames=self._ranging_frames, skipped=self._skipped,
                             crc_errors=s.crc_errors, bad_headers=s.bad_headers, malformed=s.malformed,
                             bytes_discarded=s.bytes_discarded, gaps=q.gaps, lost=q.lost,
                             duplicates=q.duplicates, restarts=q.restarts)

    # -- link ------------------------------------------------------------------------------------------
    def _now_us(self) -> int:
        return int(time.monotonic() * 1e6)

    def _raise_fault(self, reason: str) -> DeviceFault:
        with self._cond:
            self._fault = reason
            self._cond.notify_all()
        return DeviceFault(reason, device=self.device)

    def _send(self, cmd: int, value: int | None) -> None:
        serial = import_serial()
        try:
            self._serial.write(p.command(self._host_seq, self._now_us(), cmd, value))
        except (serial.SerialException, OSError) as exc:
            raise self._raise_fault(f"port vanished while writing: {exc}") from None
        self._host_seq += 1

    def _read_loop(self) -> None:
        """The reader thread: decode what arrives until ``disconnect`` or a fault (kept for capture)."""
        ordinary_scheduling()  # never at a realtime priority inherited from a control thread
        port = self._serial  # the port of this connection, even if disconnect gave up waiting for us
        with contextlib.suppress(DriverError):
            while not self._stop_reading.is_set() and self._fault is None:
                self._read(port)

    def _read(self, port: Any) -> None:
        """Decode what one read of ``port`` returns (waiting up to one read slice for a first byte);
        RANGING frames wait for ``capture`` with the clock's time of their arrival."""
        serial = import_serial()
        try:
            data = port.read(max(port.in_waiting, 1))
        except (serial.SerialException, OSError) as exc:
            raise self._raise_fault(f"port vanished: {exc}") from None
        arrived = self._clock.now()
        with self._cond:
            self._bytes_read += len(data)
            for frame in self._parser.feed(data):
                if isinstance(frame, p.CommandFrame):
                    continue  # our own commands, echoed by a loop:// port
                self._sequence.add(frame.seq)
                if isinstance(frame, p.RangingFrame):
                    self._ranging_frames += 1
                    self._at_last_frame = (self._parser.stats.bytes_discarded, self._parser.stats.crc_errors,
                                           self.last_status)
                    self._pending.append((arrived, frame))
                    self._cond.notify_all()
                elif isinstance(frame, p.StatusFrame):
                    self.last_status = frame
                    if frame.result != p.RESULT_OK:
                        raise self._raise_fault(
                            f"the bridge answered command 0x{frame.command:02x} with "
                            f"'{p.RESULT_TEXT.get(frame.result, f'result {frame.result}')}'"
                            + (f" (last message: {self.messages[-1]})" if self.messages else ""))
                else:
                    self.messages.append(frame.text)

    def _silence(self) -> str:
        """Why no RANGING frame came, from what did since the last one (or the connection; the caller
        holds the lock): a status saying the bridge no longer ranges (it restarted), bytes that made no
        frame, or nothing (a loop:// port's echo of our own commands is nothing)."""
        discarded_before, crc_before, status_before = self._at_last_frame
        stats, status = self._parser.stats, self.last_status
        discarded, crc = stats.bytes_discarded - discarded_before, stats.crc_errors - crc_before
        if status is not None and status is not status_before and not status.ranging:
            return "the bridge says it is not ranging (it restarted?); reconnect to start it again"
        if discarded == 0 and crc == 0:
            return "the port is silent"
        return (f"{discarded} bytes arrived that made no frame ({crc} failed their CRC): check the baud "
                f"rate and the cable")

    def latched_fault(self) -> DeviceFault | None:
        """The fault the reader thread latched (the port vanished, the bridge refused a command), or the
        silence a capture found; read without the lock: one reference."""
        fault = self._fault
        return None if fault is None else DeviceFault(f"faulted: {fault}; reconnect to clear",
                                                      device=self.device)

    # -- capture ---------------------------------------------------------------------------------------
    def capture(self) -> DepthFrame:
        """The newest RANGING frame not returned yet, stamped with its arrival; older ones still waiting
        are dropped (their link counters are kept). Raises ``DriverError`` when faulted, silent for
        ``timeout_s`` or gone."""
        if self._serial is None:
            raise DriverError("capture while disconnected; call connect() first", device=self.device)
        deadline = time.monotonic() + self.config.timeout_s
        with self._cond:
            while not self._pending and self._fault is None:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    self._fault = f"no frame for {self.config.timeout_s:g} s: {self._silence()}"
                    raise DeviceFault(self._fault, device=self.device)
                self._cond.wait(left)
            fault = self.latched_fault()
            if fault is not None:
                raise fault
            arrived, raw = self._pending[-1]
            self._skipped += len(self._pending) - 1
            self._pending.clear()
        self.last_raw = raw
        frame = depth_frame(raw, seq=self._seq, timestamp=arrived, fov_deg=self.config.fov_deg,
                            valid_statuses=self.config.valid_statuses, correction=self._correction)
        self._seq += 1
        return frame
