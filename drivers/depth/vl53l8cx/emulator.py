"""A VL53L8CX bridge emulator: speaks the bridge's protocol (``docs/vl53l8cx-serial.md``) on a
pseudo-terminal or a TCP socket, with ranging data rendered by the simulated ToF sensor.

It behaves like the firmware in ``deploy/firmware/``: after start it sends a TEXT banner and a STATUS
(command 0), does not range until START, answers every command with a STATUS, refuses a frequency above
the sensor's limit at the current resolution (15 Hz at 8x8, 60 Hz at 4x4) and lowers the frequency to the
new limit when the resolution changes. Ranging frames leave at the commanded frequency on the wall clock,
numbered like every frame the device sends by one sequence counter, stamped with the device's
microseconds.

The scene (:class:`SimToFSource`): a simulated scene seen from a pose that may move, rendered by
:class:`drivers.depth.sim_tof.SimToF` with the noise of ``noise`` and quantised to the sensor's integers;
by default (:meth:`SimToFSource.fixed`) a shipped object on a table, seen by a sensor at a fixed pose
(``standoff_m`` from the object's half height, looking down at it from the side at ``tilt_deg`` from
vertical).

Faults for tests and commissioning drills (:class:`EmulatorFaults`): garbage ahead of the first answer,
corrupted frames
(one payload bit flipped after the CRC was computed), dropped frames (a sequence gap), frames written in
small chunks (split reads), and a disconnect after a number of frames. Ranging frames are counted from
0 for the first one the emulator sends.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.clock import SimClock
from drivers.depth.config import DepthNoiseConfig, SimToFConfig
from drivers.depth.sim_tof import SimToF
from drivers.depth.vl53l8cx import protocol as p
from drivers.sim.objects import load_object
from drivers.sim.scene import SimScene
from drivers.transforms import look_at

OUTBOX_LIMIT = 8192
"""Bytes the emulator buffers for a reader that does not keep up; frames beyond are dropped, as a UART's
transmit buffer would drop them (the reader sees a sequence gap)."""
SPLIT_CHUNK_MAX = 32
SPLIT_PAUSE_S = 0.001
BANNER = "cell VL53L8CX bridge emulator, protocol 1"
HISTORY = 1000
"""Ranging frames the emulator remembers as rendered (before any injected fault), for tests."""


@dataclass(frozen=True)
class ZoneData:
    """One measurement as the sensor's integers, row-major zones (see ``protocol.RangingFrame``)."""

    distance_mm: NDArray[np.int16]
    range_sigma_mm: NDArray[np.uint16]
    target_status: NDArray[np.uint8]
    reflectance_pct: NDArray[np.uint8]
    nb_target_detected: NDArray[np.uint8]


ZoneSource = Callable[[p.Resolution], ZoneData]
"""What the emulator measures with: the zones at a resolution (e.g. :class:`SimToFSource`)."""


@dataclass(frozen=True)
class EmulatorFaults:
    """Faults to inject. ``garbage_bytes`` random bytes (with stray magics) sent just before the answer
    to the host's first command (boot noise arriving as the host connects: what a pseudo-terminal holds
    before the host opens it is flushed by the opening);
    ``corrupt_frames`` ranging frame indices sent with one payload bit flipped, plus every
    ``corrupt_every``-th frame (0: none); ``drop_frames`` ranging frame indices numbered but never sent;
    ``split`` writes every frame in chunks of 1..32 bytes, 1 ms apart; ``disconnect_after`` closes the
    link once that many ranging frames were sent (None: never)."""

    garbage_bytes: int = 0
    corrupt_frames: frozenset[int] = frozenset()
    corrupt_every: int = 0
    drop_frames: frozenset[int] = frozenset()
    split: bool = False
    disconnect_after: int | None = None

    def corrupts(self, index: int) -> bool:
        return index in self.corrupt_frames or (self.corrupt_every > 0 and index % self.corrupt_every
                                                 == self.corrupt_every - 1)


class SimToFSource:
    """Renders :class:`ZoneData` of a simulated scene with the simulated ToF sensor, seen from the pose
    ``view()`` returns when a frame is ranged (T_base_sensor, 4x4, base frame [m]): a fixed viewpoint
    (:meth:`fixed`, the module docstring's scene) or an arm's (a test's controller peer, so that what the
    emulator sees follows the arm). ``seed`` fixes the noise."""

    def __init__(self, scene: SimScene, view: Callable[[], NDArray[np.float64]], *, fov_deg: float = 45.0,
                 noise: DepthNoiseConfig | None = None, seed: int = 0) -> None:
        self._scene = scene
        self._view = view
        self._noise = noise if noise is not None else DepthNoiseConfig(sigma0_m=0.004, k_per_m=0.01)
        self._fov_deg = fov_deg
        self._rng = np.random.default_rng(seed)
        self._clock = SimClock()
        self._sensors: dict[p.Resolution, SimToF] = {}

    @classmethod
    def fixed(cls, object_name: str = "cube", *, standoff_m: float = 0.3, tilt_deg: float = 20.0,
              fov_deg: float = 45.0, noise: DepthNoiseConfig | None = None, seed: int = 0) -> SimToFSource:
        """A shipped object at the base frame's origin on a 1.2 m table, seen ``standoff_m`` from its
        half height at ``tilt_deg`` from vertical."""
        mesh = load_object(object_name)
        scene = SimScene(mesh, np.eye(4), table_center_xy=(0.0, 0.0), table_size_xy=(1.2, 1.2))
        height = float(mesh.extents_m[2])
        tilt = np.deg2rad(tilt_deg)
        eye = np.array([-standoff_m * np.sin(tilt), 0.0, height / 2.0 + standoff_m * np.cos(tilt)])
        T_base_sensor = look_at(eye, np.array([0.0, 0.0, height / 2.0]))
        return cls(scene, lambda: T_base_sensor, fov_deg=fov_deg, noise=noise, seed=seed)

    def _sensor(self, resolution: p.Resolution) -> SimToF:
        if resolution not in self._sensors:
            cfg = SimToFConfig(type="sim-tof", resolution=resolution, fov_deg=self._fov_deg,
                               noise=self._noise)
            sensor = SimToF(cfg, self._scene, self._view, self._clock, self._rng)
            sensor.connect()
            self._sensors[resolution] = sensor
        return self._sensors[resolution]

    def __call__(self, resolution: p.Resolution) -> ZoneData:
        z = self._sensor(resolution).capture().zones
        assert z is not None  # a SimToF frame always has zones
        target = z.nb_targets > 0
        mm = np.where(target, np.rint(z.distance_m * 1000.0), 0.0)
        sigma = np.where(target, np.rint(z.sigma_m * 1000.0), 0.0)
        refl = np.where(target, np.rint(z.reflectance_pct), 0.0)
        return ZoneData(distance_mm=np.clip(mm, 0, np.iinfo(np.int16).max).astype(np.int16),
                        range_sigma_mm=np.clip(sigma, 0, np.iinfo(np.uint16).max).astype(np.uint16),
                        target_status=z.status.astype(np.uint8), reflectance_pct=refl.astype(np.uint8),
                        nb_target_detected=z.nb_targets.astype(np.uint8))


@dataclass
class EmulatorCounters:
    """What the emulator did: ranging frames rendered (``frames``), ``sent``, ``corrupted``, ``dropped``
    on purpose, ``overflowed`` (reader too slow), and the ``commands`` it received."""

    frames: int = 0
    sent: int = 0
    corrupted: int = 0
    dropped: int = 0
    overflowed: int = 0
    commands: list[int] = field(default_factory=list)


class _Link:
    """The emulator's end of a pseudo-terminal or of one accepted TCP connection (non-blocking fd)."""

    def __init__(self, url: str, fd: int | None, listener: socket.socket | None = None,
                 keep_open: int | None = None) -> None:
        self.url = url
        self.fd = fd
        self.listener = listener
        self._client: socket.socket | None = None
        self._keep_open = keep_open

    @classmethod
    def pty(cls) -> _Link:
        master, slave = os.openpty()
        # Raw from the start: the line discipline must neither echo nor translate the binary frames
        # before a client opens the terminal (pyserial sets raw mode itself when it does).
        tty.setraw(slave)
        os.set_blocking(master, False)
        return cls(os.ttyname(slave), master, keep_open=slave)

    @classmethod
    def tcp(cls, host: str, port: int) -> _Link:
        listener = socket.create_server((host, port))
        listener.setblocking(False)
        bound_host, bound_port = listener.getsockname()[:2]
        return cls(f"socket://{bound_host}:{bound_port}", None, listener=listener)

    def accept(self) -> bool:
        """Take a waiting TCP client (replacing a previous one); True when a new client came."""
        if self.listener is None:
            return False
        try:
            client, _ = self.listener.accept()
        except BlockingIOError:
            return False
        if self._client is not None:
            self._client.close()
        client.setblocking(False)
        self._client = client
        self.fd = client.fileno()
        return True

    def drop_client(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
            self.fd = None

    def close(self) -> None:
        if self.listener is not None:
            self.drop_client()
            self.listener.close()
            self.listener = None
        elif self.fd is not None:
            os.close(self.fd)
        self.fd = None
        if self._keep_open is not None:
            os.close(self._keep_open)
            self._keep_open = None


class VL53L8CXEmulator:
    """The emulated bridge (see the module docstring). Create it with :meth:`on_pty` or :meth:`on_tcp`,
    point a driver at :attr:`url`, and run it with :meth:`start` (a thread) or :meth:`run` (blocking)."""

    def __init__(self, link: _Link, source: ZoneSource, faults: EmulatorFaults | None = None,
                 seed: int = 0) -> None:
        self._link = link
        self._source = source
        self.faults = faults if faults is not None else EmulatorFaults()
        self._rng = np.random.default_rng(seed)
        self._parser = p.FrameParser()
        self._outbox = bytearray()
        self._seq = 0
        self._t0 = time.monotonic()
        self.ranging = False
        self.resolution: p.Resolution = 8
        self.frequency_hz = 15
        self._next_frame_t = 0.0
        self.counters = EmulatorCounters()
        self.history: deque[p.RangingFrame] = deque(maxlen=HISTORY)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    @classmethod
    def on_pty(cls, source: ZoneSource, faults: EmulatorFaults | None = None,
               seed: int = 0) -> VL53L8CXEmulator:
        return cls(_Link.pty(), source, faults, seed)

    @classmethod
    def on_tcp(cls, source: ZoneSource, faults: EmulatorFaults | None = None, seed: int = 0,
               host: str = "127.0.0.1", port: int = 0) -> VL53L8CXEmulator:
        """Listen on ``host``:``port`` (0: a free port); one client at a time."""
        return cls(_Link.tcp(host, port), source, faults, seed)

    @property
    def url(self) -> str:
        """The pyserial URL of the emulated device (a pseudo-terminal path or ``socket://host:port``)."""
        return self._link.url

    # -- frames ----------------------------------------------------------------------------------------
    def _now_us(self) -> int:
        return int((time.monotonic() - self._t0) * 1e6)

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq += 1
        return seq

    def _queue(self, data: bytes) -> bool:
        if len(self._outbox) + len(data) > OUTBOX_LIMIT:
            return False
        self._outbox += data
        return True

    def _garbage(self) -> None:
        junk = bytearray(self._rng.integers(0, 256, self.faults.garbage_bytes, dtype=np.uint8).tobytes())
        for k in range(0, len(junk) - 1, 97):  # stray magics, so that resynchronisation is exercised
            junk[k:k + 2] = p.MAGIC
        self._outbox += junk

    def _hello(self) -> None:
        self._queue(p.encode(p.TextFrame(self._next_seq(), self._now_us(), BANNER)))
        self._status(0, p.RESULT_OK)

    def _status(self, command: int, result: int) -> None:
        self._queue(p.encode(p.StatusFrame(self._next_seq(), self._now_us(), command, result, self.ranging,
                                           self.resolution, self.frequency_hz)))

    def _handle(self, frame: p.Frame) -> None:
        if not isinstance(frame, p.CommandFrame):
            return
        if not self.counters.commands and self.faults.garbage_bytes:
            self._garbage()
        self.counters.commands.append(frame.command)
        result = p.RESULT_OK
        if frame.command == p.CMD_START:
            self.ranging = True
            self._next_frame_t = time.monotonic()
        elif frame.command == p.CMD_STOP:
            self.ranging = False
        elif frame.command == p.CMD_SET_RESOLUTION:
            if p.is_resolution(frame.value):
                self.resolution = frame.value
                self.frequency_hz = min(self.frequency_hz, p.MAX_FREQUENCY_HZ[self.resolution])
            else:
                result = p.RESULT_INVALID_PARAMETER
        elif frame.command == p.CMD_SET_FREQUENCY:
            if frame.value is not None and 1 <= frame.value <= p.MAX_FREQUENCY_HZ[self.resolution]:
                self.frequency_hz = frame.value
            else:
                result = p.RESULT_INVALID_PARAMETER
        self._status(frame.command, result)

    def _ranging_frame(self) -> None:
        index = self.counters.frames
        self.counters.frames += 1
        z = self._source(self.resolution)
        frame = p.RangingFrame(self._next_seq(), self._now_us(), self.resolution, z.distance_mm,
                               z.range_sigma_mm, z.target_status, z.reflectance_pct, z.nb_target_detected)
        self.history.append(frame)
        data = bytearray(p.encode(frame))
        if index in self.faults.drop_frames:
            self.counters.dropped += 1
            return
        if self.faults.corrupts(index):
            k = p.HEADER_SIZE + int(self._rng.integers(0, len(data) - p.HEADER_SIZE - p.CRC_SIZE))
            data[k] ^= 1 << int(self._rng.integers(0, 8))
            self.counters.corrupted += 1
        if self._queue(bytes(data)):
            self.counters.sent += 1
        else:
            self.counters.overflowed += 1

    # -- I/O -------------------------------------------------------------------------------------------
    def _write(self) -> None:
        fd = self._link.fd
        if fd is None or not self._outbox:
            return
        n = int(self._rng.integers(1, SPLIT_CHUNK_MAX + 1)) if self.faults.split else len(self._outbox)
        try:
            written = os.write(fd, self._outbox[:n])
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno in (errno.EPIPE, errno.ECONNRESET, errno.EIO):
                self._lost_client()
                return
            raise
        del self._outbox[:written]

    def _read(self) -> None:
        fd = self._link.fd
        if fd is None:
            return
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.ECONNRESET):
                self._lost_client()
                return
            raise
        if not data and self._link.listener is not None:
            self._lost_client()
            return
        for frame in self._parser.feed(data):
            self._handle(frame)

    def _lost_client(self) -> None:
        """A TCP client went away: wait for the next one, with the device's state kept (a board keeps
        ranging when the host closes the port)."""
        self._link.drop_client()
        self._outbox.clear()

    def _step(self) -> bool:
        """One pass of the loop; False once the emulator has disconnected on purpose."""
        if self._link.accept():
            self._outbox.clear()
            self._hello()
        now = time.monotonic()
        wait = 0.05
        limit = self.faults.disconnect_after
        finishing = limit is not None and self.counters.sent >= limit  # no more frames: drain, then close
        if self.ranging and not finishing:
            period = 1.0 / self.frequency_hz
            if now >= self._next_frame_t:
                self._ranging_frame()
                # a late loop does not send a burst to catch up
                self._next_frame_t = max(self._next_frame_t + period, now)
            wait = min(wait, max(0.0, self._next_frame_t - now))
        if self._outbox and self._link.fd is not None:
            self._write()
            wait = min(wait, SPLIT_PAUSE_S if self.faults.split else 0.0)
        if finishing and not self._outbox:
            return False
        fds = [fd for fd in (self._link.fd, self._link.listener.fileno() if self._link.listener else None)
               if fd is not None]
        readable, _, _ = select.select(fds, [], [], wait)
        if self._link.fd is not None and self._link.fd in readable:
            self._read()
        return True

    def run(self) -> None:
        """Serve until :meth:`stop` or the configured disconnect; closes the link at the end."""
        if self._link.listener is None:
            self._hello()
        try:
            while not self._stop.is_set() and self._step():
                pass
        finally:
            self.close()

    def start(self) -> VL53L8CXEmulator:
        """Serve from a daemon thread; returns self."""
        self._thread = threading.Thread(target=self.run, name="vl53l8cx-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the link (the client sees the device vanish)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.close()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):
                self._link.close()

    def __enter__(self) -> VL53L8CXEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
