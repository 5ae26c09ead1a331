"""The VL53L8CX bridge's binary frame format (``docs/vl53l8cx-serial.md`` is the normative description).

Every frame, in both directions, is little-endian::

    offset  size  field
    0       2     magic 0xA5 0x5C
    2       1     version (1)
    3       1     frame type
    4       2     payload length L [bytes], at most MAX_PAYLOAD
    6       4     sequence number (per sender, +1 for every frame it sends, wraps at 2**32)
    10      4     timestamp [us] of the sender's clock (wraps at 2**32)
    14      L     payload
    14 + L  2     CRC-16/CCITT-FALSE of bytes 0 .. 14 + L - 1 (magic included)

Device to host: RANGING (0x01), STATUS (0x02), TEXT (0x03). Host to device: START (0x81), STOP (0x82),
SET_RESOLUTION (0x83, u8 4 or 8), SET_FREQUENCY (0x84, u8 [Hz]), QUERY (0x85).

:class:`FrameParser` turns an arbitrary byte stream into decoded frames: it skips garbage up to the next
magic, rejects headers of another version or with an impossible length, and never returns a frame whose
CRC does not match. After a CRC error it moves on by one byte only (the length field of a corrupted frame
cannot be trusted, so the next frame may start inside it). A corrupted length field that announces a
longer frame delays the frames after it until that many bytes have arrived (at most MAX_PAYLOAD + 16,
about two 8x8 frames); they are not lost.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, field
from typing import Literal, TypeGuard

import numpy as np
from numpy.typing import NDArray

MAGIC = b"\xa5\x5c"
VERSION = 1
HEADER = struct.Struct("<2sBBHII")
HEADER_SIZE = HEADER.size  # 14
CRC_SIZE = 2
MAX_PAYLOAD = 1024
"""A header announcing a longer payload is not a header (the longest frame, 8x8 ranging, has 450 bytes)."""

RANGING = 0x01
STATUS = 0x02
TEXT = 0x03
CMD_START = 0x81
CMD_STOP = 0x82
CMD_SET_RESOLUTION = 0x83
CMD_SET_FREQUENCY = 0x84
CMD_QUERY = 0x85
COMMANDS: frozenset[int] = frozenset({CMD_START, CMD_STOP, CMD_SET_RESOLUTION, CMD_SET_FREQUENCY,
                                      CMD_QUERY})
COMMANDS_WITH_VALUE: frozenset[int] = frozenset({CMD_SET_RESOLUTION, CMD_SET_FREQUENCY})

RESULT_OK = 0
RESULT_INVALID_PARAMETER = 1
RESULT_SENSOR_ERROR = 2
RESULT_TEXT: dict[int, str] = {RESULT_OK: "ok", RESULT_INVALID_PARAMETER: "invalid parameter",
                               RESULT_SENSOR_ERROR: "sensor error"}

Resolution = Literal[4, 8]
"""A resolution the VL53L8CX supports, in zones per side."""

MAX_FREQUENCY_HZ: dict[Resolution, int] = {4: 60, 8: 15}
"""Highest ranging frequency [Hz] the VL53L8CX allows at each resolution (zones per side)."""


def is_resolution(value: int | None) -> TypeGuard[Resolution]:
    """True when ``value`` (zones per side) is a resolution the VL53L8CX supports."""
    return value in MAX_FREQUENCY_HZ

ZONE = np.dtype([("distance_mm", "<i2"), ("range_sigma_mm", "<u2"), ("target_status", "u1"),
                 ("reflectance_pct", "u1"), ("nb_target_detected", "u1")])
"""One zone of a RANGING payload, 7 bytes."""
RANGING_PREFIX = struct.Struct("<BB")  # resolution (zones per side), targets per zone (1)
STATUS_PAYLOAD = struct.Struct("<BBBBB")  # command answered, result, ranging, resolution, frequency [Hz]

U32 = 1 << 32


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR
    (check value of b"123456789": 0x29B1). ``binascii.crc_hqx`` is exactly this CRC with that seed."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, eq=False)
class RangingFrame:
    """One VL53L8CX measurement as the bridge sends it: ``resolution`` zones per side (4 or 8), per-zone
    arrays of length resolution**2, row-major from the top-left zone as seen in the sensor frame (x right,
    y down): ``distance_mm`` [mm], ``range_sigma_mm`` [mm], ``target_status`` (ST's codes),
    ``reflectance_pct`` [%], ``nb_target_detected``. ``seq`` and ``timestamp_us`` [us] are the device's."""

    seq: int
    timestamp_us: int
    resolution: int
    distance_mm: NDArray[np.int16]
    range_sigma_mm: NDArray[np.uint16]
    target_status: NDArray[np.uint8]
    reflectance_pct: NDArray[np.uint8]
    nb_target_detected: NDArray[np.uint8]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RangingFrame) and encode(self) == encode(other)

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class StatusFrame:
    """The device's answer to a command (``command`` its type, 0 when unsolicited, e.g. after boot) with
    its state afterwards: ``ranging``, ``resolution`` (zones per side), ``frequency_hz`` [Hz]."""

    seq: int
    timestamp_us: int
    command: int
    result: int
    ranging: bool
    resolution: int
    frequency_hz: int


@dataclass(frozen=True)
class TextFrame:
    """A UTF-8 message from the device (boot banner, sensor errors), for people."""

    seq: int
    timestamp_us: int
    text: str


@dataclass(frozen=True)
class CommandFrame:
    """A host command; ``value`` is the u8 argument of SET_RESOLUTION / SET_FREQUENCY, else None."""

    seq: int
    timestamp_us: int
    command: int
    value: int | None = None


Frame = RangingFrame | StatusFrame | TextFrame | CommandFrame


def frame_bytes(frame_type: int, seq: int, timestamp_us: int, payload: bytes) -> bytes:
    """A complete frame: header, ``payload`` and CRC. ``seq`` and ``timestamp_us`` wrap at 2**32."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes is longer than {MAX_PAYLOAD}")
    body = HEADER.pack(MAGIC, VERSION, frame_type, len(payload), seq % U32, timestamp_us % U32) + payload
    return body + struct.pack("<H", crc16(body))


def ranging_payload(resolution: int, distance_mm: NDArray[np.integer], range_sigma_mm: NDArray[np.integer],
                    target_status: NDArray[np.integer], reflectance_pct: NDArray[np.integer],
                    nb_target_detected: NDArray[np.integer]) -> bytes:
    """The RANGING payload; each array has resolution**2 values that fit its field's type."""
    if resolution not in MAX_FREQUENCY_HZ:
        raise ValueError(f"resolution must be 4 or 8 zones per side, got {resolution}")
    zones = np.zeros(resolution * resolution, dtype=ZONE)
    for name, values in (("distance_mm", distance_mm), ("range_sigma_mm", range_sigma_mm),
                         ("target_status", target_status), ("reflectance_pct", reflectance_pct),
                         ("nb_target_detected", nb_target_detected)):
        v = np.asarray(values).reshape(-1)
        info = np.iinfo(ZONE[name])
        if v.shape != zones.shape or np.any(v < info.min) or np.any(v > info.max):
            raise ValueError(f"{name}: need {zones.size} integers in [{info.min}, {info.max}]")
        zones[name] = v
    return RANGING_PREFIX.pack(resolution, 1) + zones.tobytes()


def encode(frame: Frame) -> bytes:
    """The bytes of a decoded frame; ``decode(encode(f)) == f`` for every frame the parser can return."""
    if isinstance(frame, RangingFrame):
        payload = ranging_payload(frame.resolution, frame.distance_mm, frame.range_sigma_mm,
                                  frame.target_status, frame.reflectance_pct, frame.nb_target_detected)
        return frame_bytes(RANGING, frame.seq, frame.timestamp_us, payload)
    if isinstance(frame, StatusFrame):
        payload = STATUS_PAYLOAD.pack(frame.command, frame.result, int(frame.ranging), frame.resolution,
                                      frame.frequency_hz)
        return frame_bytes(STATUS, frame.seq, frame.timestamp_us, payload)
    if isinstance(frame, TextFrame):
        return frame_bytes(TEXT, frame.seq, frame.timestamp_us, frame.text.encode("utf-8"))
    payload = b"" if frame.value is None else bytes([frame.value])
    return frame_bytes(frame.command, frame.seq, frame.timestamp_us, payload)


def command(seq: int, timestamp_us: int, command_type: int, value: int | None = None) -> bytes:
    """The bytes of a host command."""
    if command_type not in COMMANDS:
        raise ValueError(f"0x{command_type:02x} is not a command")
    if (value is not None) != (command_type in COMMANDS_WITH_VALUE):
        raise ValueError(f"command 0x{command_type:02x} takes {'one' if value is None else 'no'} value")
    return encode(CommandFrame(seq, timestamp_us, command_type, value))


def _decode_payload(frame_type: int, seq: int, ts: int, payload: bytes) -> Frame | None:
    """The frame a CRC-checked payload holds, or None when it does not fit its type."""
    if frame_type == RANGING:
        if len(payload) < RANGING_PREFIX.size:
            return None
        resolution, targets = RANGING_PREFIX.unpack_from(payload)
        n = resolution * resolution
        if resolution not in MAX_FREQUENCY_HZ or targets != 1 or len(payload) != RANGING_PREFIX.size + 7 * n:
            return None
        z = np.frombuffer(payload, dtype=ZONE, offset=RANGING_PREFIX.size)
        return RangingFrame(seq, ts, resolution, z["distance_mm"].astype(np.int16),
                            z["range_sigma_mm"].astype(np.uint16), z["target_status"].copy(),
                            z["reflectance_pct"].copy(), z["nb_target_detected"].copy())
    if frame_type == STATUS:
        if len(payload) != STATUS_PAYLOAD.size:
            return None
        cmd, result, ranging, resolution, freq = STATUS_PAYLOAD.unpack(payload)
        if ranging > 1:
            return None
        return StatusFrame(seq, ts, cmd, result, bool(ranging), resolution, freq)
    if frame_type == TEXT:
        try:
            return TextFrame(seq, ts, payload.decode("utf-8"))
        except UnicodeDecodeError:
            return None
    if frame_type in COMMANDS:
        expected = 1 if frame_type in COMMANDS_WITH_VALUE else 0
        if len(payload) != expected:
            return None
        return CommandFrame(seq, ts, frame_type, payload[0] if expected else None)
    return None


@dataclass
class ParserStats:
    """What a :class:`FrameParser` has seen: ``frames`` decoded; ``crc_errors`` headers whose frame failed
    the CRC; ``bad_headers`` magics followed by another version or an impossible length; ``malformed``
    frames with a good CRC whose payload does not fit their type (unknown type, wrong length);
    ``bytes_discarded`` bytes skipped while looking for a frame."""

    frames: int = 0
    crc_errors: int = 0
    bad_headers: int = 0
    malformed: int = 0
    bytes_discarded: int = 0


@dataclass
class FrameParser:
    """Incremental decoder of a byte stream; ``feed`` returns the frames completed by the new bytes."""

    stats: ParserStats = field(default_factory=ParserStats)
    _buf: bytearray = field(default_factory=bytearray)

    def _discard(self, n: int) -> None:
        del self._buf[:n]
        self.stats.bytes_discarded += n

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        buf = self._buf
        buf += data
        out: list[Frame] = []
        while True:
            start = buf.find(MAGIC)
            if start < 0:
                # Keep a trailing first magic byte: the rest of the magic may come with the next read.
                self._discard(len(buf) - (1 if buf.endswith(MAGIC[:1]) else 0))
                return out
            if start:
                self._discard(start)
            if len(buf) < HEADER_SIZE:
                return out
            _, version, frame_type, length, seq, ts = HEADER.unpack_from(buf)
            if version != VERSION or length > MAX_PAYLOAD:
                self.stats.bad_headers += 1
                self._discard(1)
                continue
            end = HEADER_SIZE + length
            if len(buf) < end + CRC_SIZE:
                return out
            (crc,) = struct.unpack_from("<H", buf, end)
            if crc != crc16(memoryview(buf)[:end]):
                self.stats.crc_errors += 1
                self._discard(1)
                continue
            frame = _decode_payload(frame_type, seq, ts, bytes(buf[HEADER_SIZE:end]))
            del buf[:end + CRC_SIZE]
            if frame is None:
                self.stats.malformed += 1
            else:
                self.stats.frames += 1
                out.append(frame)


@dataclass
class SequenceCounter:
    """Tracks a sender's sequence numbers: ``gaps`` jumps forward by more than one, ``lost`` the frames
    they skipped, ``duplicates`` repeated numbers, ``restarts`` jumps backwards (a device reset; the
    count starts again there, with no gap counted). A difference of 2**31 or more modulo 2**32 counts
    as backwards."""

    last: int | None = None
    gaps: int = 0
    lost: int = 0
    duplicates: int = 0
    restarts: int = 0

    def add(self, seq: int) -> None:
        if self.last is not None:
            step = (seq - self.last) % U32
            if step == 0:
                self.duplicates += 1
            elif step >= U32 // 2:
                self.restarts += 1
            elif step > 1:
                self.gaps += 1
                self.lost += step - 1
        self.last = seq
