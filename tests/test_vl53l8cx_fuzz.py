"""Structure-aware fuzzing of the VL53L8CX serial link (``docs/vl53l8cx-serial.md``).

A device stream is built from well-formed frames (ranging frames with any resolution, status, distance
and target count the fields can hold, status and text frames) and from faults, each with a known effect:
frames with one field mutated and their CRC recomputed (type, resolution, targets per zone, payload
length, status fields, text encoding: malformed), headers with another version or an impossible length
(bad headers), frames with one bit flipped or cut short (CRC errors or bad headers, depending on what the
header they leave behind says), garbage, and sequence numbers dropped, repeated, restarted and wrapped.
The stream is then cut at random points.

Every expectation comes from the injection, not from the parser: which frames come out and after which
byte, each counter of the parser and of the sequence check, and for the real driver reading the stream from
a pseudo-terminal, which frame each ``capture`` returns, that it is within the spec, how many were skipped,
and that the only exception it raises is the fault a failing STATUS asks for.
"""

from __future__ import annotations

import os
import re
import struct
import time
import tty
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from drivers.depth.base import DepthFrame
from drivers.depth.config import VL53L8CXConfig
from drivers.depth.vl53l8cx import protocol as p
from drivers.depth.vl53l8cx.serial_driver import LinkStats, VL53L8CXSerial
from drivers.errors import CellError, DriverError

FUZZ = settings(derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])

U32 = 2**32
u32 = st.integers(0, U32 - 1)
DOCUMENTED_STATUSES = (*range(14), 255)
MAX_STREAM = 3800
"""Bytes of the longest stream given to the driver: a pseudo-terminal holds 4 kB unread (see
``_wait_landed``)."""
NO_MAGIC_BYTE = bytes.maketrans(p.MAGIC, b"\x00\x00")


def edgy(lo: int, hi: int) -> st.SearchStrategy[int]:
    """Integers in [lo, hi], half of them one of the two bounds (where off-by-one mistakes live)."""
    return st.one_of(st.sampled_from((lo, hi)), st.integers(lo, hi))


@dataclass
class Numbering:
    """The device's sequence numbers as the stream hands them out, and the sequence counters the host
    must end with, counted from what happened to each numbered frame (delivered, lost, repeated, after a
    restart), not from the numbers' arithmetic. A restart sends the count back by ``back`` from the last
    delivered number, at least 64 and at most 2**31 (the document's "backwards")."""

    next: int
    last: int | None = None
    unseen: int = 0
    restarted: bool = False
    gaps: int = 0
    lost: int = 0
    duplicates: int = 0
    restarts: int = 0

    def take(self) -> int:
        seq = self.next
        self.next = (seq + 1) % U32
        return seq

    def lose(self) -> None:
        self.unseen += 1

    def deliver(self, seq: int) -> None:
        if self.last is not None:
            if self.restarted:
                self.restarts += 1
            elif self.unseen:
                self.gaps += 1
                self.lost += self.unseen
        self.last, self.unseen, self.restarted = seq, 0, False

    def repeat(self) -> int:
        """The last delivered number again: a duplicate, after which the count goes on as before."""
        assert self.last is not None and not self.restarted
        self.duplicates += 1
        return self.last

    def restart(self, back: int) -> None:
        self.next = ((self.last or 0) - back) % U32
        self.unseen, self.restarted = 0, True


@dataclass(frozen=True)
class Piece:
    """Bytes of the stream: a ``frame`` the host must decode from them, or a ``malformed`` frame (good
    CRC, payload unfit for its type), or (neither) bytes the host must throw away."""

    data: bytes
    frame: p.Frame | None = None
    malformed: bool = False


@dataclass
class Link:
    """A stream and what the host must make of it. ``delivered`` holds each frame to decode with the
    stream offset after which it can be (its end, or later when a corrupted header before it announced
    a longer frame); ``expected`` the parser's and sequence counters at the end of the stream; ``cuts``
    where the stream is split; ``body_length`` its length without the zero filler that lets the last
    corrupted header be judged, and ``discarded_before_filler`` the bytes to throw away before it."""

    stream: bytes
    delivered: list[tuple[int, p.Frame]]
    expected: dict[str, int]
    cuts: list[int]
    body_length: int
    discarded_before_filler: int

    def chunks(self) -> list[tuple[int, int]]:
        ends = [*self.cuts, len(self.stream)]
        return list(zip([0, *ends[:-1]], ends, strict=True))


def _ranging(draw: st.DrawFn, seq: int) -> p.RangingFrame:
    """A ranging frame with values anywhere in their fields' types, most of them plausible."""
    resolution = draw(st.sampled_from((4, 8)))
    n = resolution * resolution
    rng = np.random.default_rng(draw(u32))

    def mostly(plausible: np.ndarray, anything: np.ndarray) -> np.ndarray:
        return np.where(rng.random(n) < 0.8, plausible, anything)

    return p.RangingFrame(
        seq, draw(u32), resolution,
        distance_mm=mostly(rng.integers(-100, 4500, n), rng.integers(-32768, 32768, n)).astype(np.int16),
        range_sigma_mm=rng.integers(0, 65536, n).astype(np.uint16),
        target_status=mostly(rng.choice(DOCUMENTED_STATUSES, n), rng.integers(0, 256, n)).astype(np.uint8),
        reflectance_pct=rng.integers(0, 256, n).astype(np.uint8),
        nb_target_detected=mostly(rng.integers(0, 5, n), rng.integers(0, 256, n)).astype(np.uint8))


def _status(draw: st.DrawFn, seq: int, result: int = p.RESULT_OK) -> p.StatusFrame:
    return p.StatusFrame(seq, draw(u32), draw(st.integers(0, 255)), result, draw(st.booleans()),
                         draw(st.integers(0, 255)), draw(st.integers(0, 255)))


def _any_frame(draw: st.DrawFn, seq: int) -> bytes:
    kind = draw(st.sampled_from(("ranging", "status", "text")))
    if kind == "ranging":
        return p.encode(_ranging(draw, seq))
    if kind == "status":
        return p.encode(_status(draw, seq))
    return p.encode(p.TextFrame(seq, draw(u32), draw(st.text(max_size=30))))


def _payload(frame: bytes) -> bytes:
    return frame[p.HEADER_SIZE:-p.CRC_SIZE]


MUTATIONS = ("type", "resolution", "other sensor", "targets", "length", "status length", "status ranging",
             "text encoding")


def _malformed(draw: st.DrawFn, seq: int, mutation: str | None = None) -> bytes:
    """A frame with a good CRC whose payload does not fit its type, by ``mutation`` (None: any)."""
    ts = draw(u32)
    mutation = mutation or draw(st.sampled_from(MUTATIONS))
    ranging = _payload(p.encode(_ranging(draw, seq)))
    if mutation == "type":  # a ranging payload fits no other type (text aside)
        frame_type = draw(st.integers(0, 255).filter(lambda t: t not in (p.RANGING, p.TEXT)))
        return p.frame_bytes(frame_type, seq, ts, ranging)
    if mutation == "resolution":
        value = draw(st.integers(0, 255).filter(lambda v: v != ranging[0]))
        return p.frame_bytes(p.RANGING, seq, ts, bytes([value]) + ranging[1:])
    if mutation == "other sensor":  # consistent, but for a resolution the VL53L8CX does not have
        resolution = draw(st.integers(0, 12).filter(lambda r: r not in (4, 8)))
        zones = draw(st.binary(min_size=7 * resolution**2, max_size=7 * resolution**2))
        return p.frame_bytes(p.RANGING, seq, ts, bytes([resolution, 1]) + zones)
    if mutation == "targets":
        value = draw(st.integers(0, 255).filter(lambda v: v != 1))
        return p.frame_bytes(p.RANGING, seq, ts, ranging[:1] + bytes([value]) + ranging[2:])
    if mutation == "length":  # the edges: empty, shorter than the prefix, one byte off
        n = len(ranging)
        size = draw(st.one_of(st.sampled_from((0, 1, 2, n - 1, n + 1)), st.integers(0, n + 40)).filter(
            lambda k: k != n))
        return p.frame_bytes(p.RANGING, seq, ts, (ranging + draw(st.binary(min_size=40, max_size=40)))[:size])
    status = _payload(p.encode(_status(draw, seq)))
    if mutation == "status length":
        size = draw(st.integers(0, 20).filter(lambda n: n != len(status)))
        return p.frame_bytes(p.STATUS, seq, ts, (status * 5)[:size])
    if mutation == "status ranging":
        return p.frame_bytes(p.STATUS, seq, ts, status[:2] + bytes([draw(edgy(2, 255))]) + status[3:])
    text = draw(st.text(max_size=20)).encode()
    cut = draw(st.integers(0, len(text)))
    return p.frame_bytes(p.TEXT, seq, ts, text[:cut] + b"\xff" + text[cut:])  # never valid UTF-8


def _bad_header(draw: st.DrawFn, seq: int) -> bytes:
    """A frame whose header is not one (another version, a length above MAX_PAYLOAD), CRC recomputed."""
    data = bytearray(_any_frame(draw, seq))
    if draw(st.booleans()):
        data[2] = draw(st.integers(0, 255).filter(lambda v: v != p.VERSION))
    else:
        data[4:6] = struct.pack("<H", draw(edgy(p.MAX_PAYLOAD + 1, 0xFFFF)))
    data[-2:] = struct.pack("<H", p.crc16(data[:-2]))
    return bytes(data)


def _flipped(draw: st.DrawFn, seq: int) -> bytes:
    data = bytearray(_any_frame(draw, seq))
    bit = draw(st.integers(0, 8 * len(data) - 1))
    data[bit // 8] ^= 1 << (bit % 8)
    return bytes(data)


def _truncated(draw: st.DrawFn, seq: int) -> bytes:
    """A ranging frame cut short: when its length field survives, the receiver waits for the rest of the
    frame it announces, and the frames after it come out only once that many bytes are in."""
    data = p.encode(_ranging(draw, seq))
    # the cuts that matter most: after the magic, the length field, the header, all but the last byte
    cut = st.one_of(st.sampled_from((1, 6, p.HEADER_SIZE, len(data) - 1)), st.integers(1, len(data) - 1))
    return data[:draw(cut)]


ACTIONS = ("ranging", "ranging", "ranging", "status", "text", "drop", "duplicate", "restart", "malformed",
           "bad header", "flipped", "truncated", "truncated", "garbage")
LOST_FRAMES = {"malformed": _malformed, "bad header": _bad_header, "flipped": _flipped,
               "truncated": _truncated}


def _pieces(draw: st.DrawFn, numbering: Numbering, failing: bool) -> list[Piece]:
    pieces: list[Piece] = []
    for action in draw(st.lists(st.sampled_from(ACTIONS), min_size=2, max_size=8)):
        if action == "ranging" or (action == "duplicate" and (numbering.last is None or numbering.restarted)):
            frame: p.Frame = _ranging(draw, numbering.take())
        elif action == "duplicate":
            frame = _ranging(draw, numbering.repeat())
            pieces.append(Piece(p.encode(frame), frame))
            continue
        elif action == "status":
            frame = _status(draw, numbering.take())
        elif action == "text":
            frame = p.TextFrame(numbering.take(), draw(u32), draw(st.text(max_size=30)))
        elif action == "restart":
            numbering.restart(draw(edgy(64, 2**31)))
            continue
        elif action == "garbage":
            pieces.append(Piece(draw(st.binary(min_size=1, max_size=40)).translate(NO_MAGIC_BYTE)))
            continue
        else:  # a numbered frame that never decodes
            seq = numbering.take()
            numbering.lose()
            if action != "drop":
                pieces.append(Piece(LOST_FRAMES[action](draw, seq), malformed=action == "malformed"))
            continue
        numbering.deliver(frame.seq)
        pieces.append(Piece(p.encode(frame), frame))
    # The stream ends with a ranging frame (the driver reads only while it waits for one), or with a
    # STATUS reporting a failure, which faults the driver.
    seq = numbering.take()
    last = _status(draw, seq, draw(edgy(1, 255))) if failing else _ranging(draw, seq)
    numbering.deliver(seq)
    return [*pieces, Piece(p.encode(last), last)]


@st.composite
def links(draw: st.DrawFn, failing: bool | None = None) -> Link:
    """A stream ending with a failing STATUS when ``failing`` (None: either)."""
    numbering = Numbering(next=draw(st.one_of(st.just(0), st.integers(U32 - 8, U32 - 1), u32)))
    pieces = _pieces(draw, numbering, draw(st.booleans()) if failing is None else failing)
    body = b"".join(piece.data for piece in pieces)
    starts = np.cumsum([0, *(len(piece.data) for piece in pieces)])[:-1].tolist()
    # Every magic in the stream begins a piece: then what each fault costs is known exactly.
    padded = body + bytes(p.HEADER_SIZE + p.MAX_PAYLOAD + p.CRC_SIZE)
    magics = {m.start() for m in re.finditer(re.escape(p.MAGIC), padded)}
    assume(magics == {s for s, piece in zip(starts, pieces, strict=True) if piece.data.startswith(p.MAGIC)})

    expected = dict.fromkeys(("frames", "ranging_frames", "crc_errors", "bad_headers", "malformed",
                              "bytes_discarded"), 0)
    delivered: list[tuple[int, p.Frame]] = []
    judged = 0  # offset by which every corrupted header so far has been judged
    for start, piece in zip(starts, pieces, strict=True):
        end = start + len(piece.data)
        if piece.frame is not None:
            delivered.append((max(end, judged), piece.frame))
            expected["frames"] += 1
            expected["ranging_frames"] += isinstance(piece.frame, p.RangingFrame)
        elif piece.malformed:
            expected["malformed"] += 1
        else:
            expected["bytes_discarded"] += len(piece.data)
            if len(piece.data) >= 2 and piece.data.startswith(p.MAGIC):
                # The header the receiver reads here: this piece's bytes, then whatever follows them.
                _, version, _, length, _, _ = p.HEADER.unpack_from(padded, start)
                if version != p.VERSION or length > p.MAX_PAYLOAD:
                    expected["bad_headers"] += 1
                    judged = max(judged, start + p.HEADER_SIZE)
                else:
                    crc_at = start + p.HEADER_SIZE + length
                    assume(struct.unpack_from("<H", padded, crc_at)[0] != p.crc16(padded[start:crc_at]))
                    expected["crc_errors"] += 1
                    judged = max(judged, crc_at + p.CRC_SIZE)
    discarded_before_filler = expected["bytes_discarded"]
    stream = body + bytes(max(0, judged - len(body)))
    expected["bytes_discarded"] += len(stream) - len(body)
    expected |= {"gaps": numbering.gaps, "lost": numbering.lost, "duplicates": numbering.duplicates,
                 "restarts": numbering.restarts}
    cuts = sorted(draw(st.sets(st.integers(1, len(stream) - 1), min_size=1, max_size=12)))
    return Link(stream, delivered, expected, cuts, len(body), discarded_before_filler)


def _failing(frame: p.Frame) -> bool:
    return isinstance(frame, p.StatusFrame) and frame.result != p.RESULT_OK


@settings(FUZZ, max_examples=400)
@given(links())
def test_the_parser_decodes_exactly_the_injected_frames_and_counts_exactly_the_injected_faults(link):
    parser = p.FrameParser()
    sequence = p.SequenceCounter()
    got: list[p.Frame] = []
    for start, end in link.chunks():
        got += parser.feed(link.stream[start:end])
        # nothing is lost, nothing is held back longer than a corrupted header's announced length
        assert got == [frame for ready, frame in link.delivered if ready <= end]
    for frame in got:
        sequence.add(frame.seq)
    s = parser.stats
    counted = {"frames": s.frames, "ranging_frames": sum(isinstance(f, p.RangingFrame) for f in got),
               "crc_errors": s.crc_errors, "bad_headers": s.bad_headers, "malformed": s.malformed,
               "bytes_discarded": s.bytes_discarded, "gaps": sequence.gaps, "lost": sequence.lost,
               "duplicates": sequence.duplicates, "restarts": sequence.restarts}
    assert counted == link.expected


@pytest.mark.parametrize("mutation", MUTATIONS)
@settings(FUZZ, max_examples=25)
@given(data=st.data())
def test_every_mutation_makes_a_malformed_frame_that_costs_only_itself(mutation, data):
    good = p.StatusFrame(6, 0, 0, p.RESULT_OK, False, 8, 15), p.TextFrame(8, 0, "after")
    parser = p.FrameParser()
    bad = _malformed(data.draw, 7, mutation)
    assert parser.feed(p.encode(good[0]) + bad + p.encode(good[1])) == list(good)
    assert (parser.stats.malformed, parser.stats.crc_errors, parser.stats.bytes_discarded) == (1, 0, 0)


def _wait_read(sensor: VL53L8CXSerial, n: int) -> None:
    """Wait until the driver's reader has decoded the ``n`` bytes written so far, or stopped at a fault:
    what the master side writes reaches the slave asynchronously, and each capture must see exactly the
    stream written so far."""
    deadline = time.monotonic() + 5.0
    while sensor.stats.bytes_read < n and sensor.is_connected:
        assert time.monotonic() < deadline, f"{n} bytes written, {sensor.stats.bytes_read} read"
        time.sleep(0.0005)


def _assert_within_spec(frame: DepthFrame, raw: p.RangingFrame, valid_statuses: tuple[int, ...]) -> None:
    """A capture as the protocol document and ``DepthFrame`` describe it: resolution^2 zones with their
    central rays in the 45 degree field of view, no distance where no target, and one point per zone that
    has a target, a positive distance and a valid status, at that distance along the zone's ray."""
    n = raw.resolution**2
    assert raw.resolution in (4, 8)
    z = frame.zones
    assert z is not None
    for values in (z.distance_m, z.sigma_m, z.status, z.nb_targets, z.reflectance_pct):
        assert values.shape == (n,)
    assert z.directions.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(z.directions, axis=1), 1.0)
    assert np.all(np.abs(z.directions[:, :2]) <= z.directions[:, 2:] * np.tan(np.deg2rad(22.5)))
    has_target = raw.nb_target_detected > 0
    assert np.array_equal(np.isnan(z.distance_m), ~has_target)
    assert np.array_equal(z.status, raw.target_status)
    assert np.array_equal(z.nb_targets, raw.nb_target_detected)
    keep = has_target & (raw.distance_mm > 0) & np.isin(raw.target_status, valid_statuses)
    assert frame.points.shape == (int(keep.sum()), 3)
    np.testing.assert_allclose(np.linalg.norm(frame.points, axis=1), raw.distance_mm[keep] / 1000.0)
    np.testing.assert_allclose(frame.points, z.distance_m[keep, None] * z.directions[keep])


@pytest.mark.parametrize("failing", [False, True], ids=["ends-ranging", "ends-failing-status"])
@settings(FUZZ, max_examples=50)
@given(data=st.data())
def test_the_serial_driver_returns_only_injected_frames_within_the_spec_and_counts_exactly(failing, data):
    link = data.draw(links(failing))
    assume(len(link.stream) <= MAX_STREAM)
    master, slave = os.openpty()
    tty.setraw(slave)
    sensor = VL53L8CXSerial(VL53L8CXConfig(type="vl53l8cx", port=os.ttyname(slave), timeout_s=1.0))
    read = 0  # delivered frames captures have seen
    skipped = 0
    faulted = False
    try:
        sensor.connect()
        for start, end in link.chunks():
            os.write(master, link.stream[start:end])
            ready = [frame for at, frame in link.delivered[read:] if at <= end]
            if not any(isinstance(f, p.RangingFrame) or _failing(f) for f in ready):
                continue  # capture would wait for more
            _wait_read(sensor, end)
            read += len(ready)
            if any(_failing(f) for f in ready):
                with pytest.raises(DriverError, match="answered command") as fault:
                    sensor.capture()
                assert isinstance(fault.value, CellError)
                faulted = True
                break
            frame = sensor.capture()
            newest = [f for f in ready if isinstance(f, p.RangingFrame)]
            assert sensor.last_raw == newest[-1]  # bit for bit the newest frame the stream carried
            _assert_within_spec(frame, newest[-1], sensor.config.valid_statuses)
            skipped += len(newest) - 1
        assert read == len(link.delivered)
        if faulted:
            assert not sensor.is_connected
            with pytest.raises(DriverError, match="faulted"):
                sensor.capture()
        stats = sensor.stats
    finally:
        sensor.disconnect()
        os.close(master)
        os.close(slave)
    expected = dict(link.expected, skipped=skipped, bytes_read=stats.bytes_read)
    if faulted:  # the reader stopped at the fault, perhaps inside the filler
        filler_read = max(0, stats.bytes_read - link.body_length)
        expected["bytes_discarded"] = link.discarded_before_filler + filler_read
    else:
        assert stats.bytes_read == len(link.stream)
    assert stats == LinkStats(**expected)
