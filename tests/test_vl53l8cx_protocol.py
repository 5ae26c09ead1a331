"""The VL53L8CX bridge frame format: CRC, encode/decode round trips, and a fuzzed parser that never crashes
and never yields a frame whose CRC does not match."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.depth.vl53l8cx import protocol as p

FUZZ = settings(max_examples=150, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])

u32 = st.integers(0, 2**32 - 1)


@st.composite
def ranging_frames(draw) -> p.RangingFrame:
    res = draw(st.sampled_from([4, 8]))
    n = res * res
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    return p.RangingFrame(draw(u32), draw(u32), res,
                          rng.integers(-32768, 32768, n).astype(np.int16),
                          rng.integers(0, 65536, n).astype(np.uint16),
                          rng.integers(0, 256, n).astype(np.uint8),
                          rng.integers(0, 256, n).astype(np.uint8),
                          rng.integers(0, 256, n).astype(np.uint8))


status_frames = st.builds(p.StatusFrame, u32, u32, st.integers(0, 255), st.integers(0, 255), st.booleans(),
                          st.integers(0, 255), st.integers(0, 255))
text_frames = st.builds(p.TextFrame, u32, u32, st.text(max_size=200))  # at most 800 UTF-8 bytes
command_frames = st.one_of(
    st.builds(p.CommandFrame, u32, u32, st.sampled_from([p.CMD_START, p.CMD_STOP, p.CMD_QUERY])),
    st.builds(p.CommandFrame, u32, u32, st.sampled_from([p.CMD_SET_RESOLUTION, p.CMD_SET_FREQUENCY]),
              st.integers(0, 255)))
frames = st.one_of(ranging_frames(), status_frames, text_frames, command_frames)
# Filler without the magic's first byte: between frames it can never start a (false) frame.
garbage = st.binary(max_size=60).map(lambda b: b.replace(p.MAGIC[:1], b"\x00"))


def test_crc_is_ccitt_false():
    assert p.crc16(b"123456789") == 0x29B1
    assert p.crc16(b"") == 0xFFFF


def test_documented_layout_of_a_stop_command():
    """The bytes docs/vl53l8cx-serial.md shows for STOP with sequence 7 at 1000 us."""
    assert p.command(7, 1000, p.CMD_STOP).hex(" ") == "a5 5c 01 82 00 00 07 00 00 00 e8 03 00 00 81 12"


@FUZZ
@given(frames)
def test_encode_decode_round_trip(frame):
    data = p.encode(frame)
    parser = p.FrameParser()
    assert parser.feed(data) == [frame]
    assert parser.stats.frames == 1 and parser.stats.bytes_discarded == 0


@FUZZ
@given(st.lists(st.tuples(garbage, frames), max_size=6), garbage, st.lists(st.integers(1, 40), max_size=30))
def test_every_frame_is_recovered_through_garbage_and_split_reads(items, tail, cuts):
    stream = b"".join(g + p.encode(f) for g, f in items) + tail
    parser = p.FrameParser()
    got: list[p.Frame] = []
    pos = 0
    for size in [*cuts, len(stream)]:
        got += parser.feed(stream[pos:pos + size])
        pos += size
    assert got == [f for _, f in items]
    assert parser.stats.crc_errors == 0


@FUZZ
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_crash_nor_yield_a_bad_frame(data):
    parser = p.FrameParser()
    for frame in parser.feed(data):
        # every frame re-encodes to bytes that are in the input, CRC included: nothing was made up
        assert p.encode(frame) in data


@FUZZ
@given(st.lists(frames, min_size=1, max_size=5), st.data())
def test_a_flipped_bit_loses_only_its_frame(items, data):
    encoded = [p.encode(f) for f in items]
    k = data.draw(st.integers(0, len(items) - 1))
    bit = data.draw(st.integers(0, 8 * len(encoded[k]) - 1))
    broken = bytearray(encoded[k])
    broken[bit // 8] ^= 1 << (bit % 8)
    stream = b"".join(encoded[:k]) + bytes(broken) + b"".join(encoded[k + 1:])
    parser = p.FrameParser()
    # A flipped length bit makes the parser wait for the longer frame the header announces before it can
    # judge it; the stream going on (here: filler without a magic) lets it decide.
    got = parser.feed(stream) + parser.feed(bytes(p.MAX_PAYLOAD + p.HEADER_SIZE + p.CRC_SIZE))
    for frame in got:
        assert p.encode(frame) in stream
    # the frames before and after the broken one all come through
    assert [f for f in got if p.encode(f) != bytes(broken)] == items[:k] + items[k + 1:]
    assert bytes(broken) not in [p.encode(f) for f in got]


def test_bad_version_and_impossible_length_are_skipped():
    good = p.command(1, 0, p.CMD_START)
    other_version = bytearray(good)
    other_version[2] = 2
    too_long = bytearray(p.command(2, 0, p.CMD_STOP))
    too_long[4:6] = struct.pack("<H", p.MAX_PAYLOAD + 1)
    parser = p.FrameParser()
    assert parser.feed(bytes(other_version) + bytes(too_long) + good) == [p.CommandFrame(1, 0, p.CMD_START)]
    assert parser.stats.bad_headers == 2


def test_a_frame_with_a_good_crc_but_the_wrong_payload_is_malformed():
    parser = p.FrameParser()
    bad_ranging = p.frame_bytes(p.RANGING, 0, 0, bytes([8, 1]) + bytes(10))  # 8x8 needs 448 zone bytes
    unknown = p.frame_bytes(0x42, 1, 0, b"")
    assert parser.feed(bad_ranging + unknown) == []
    assert parser.stats.malformed == 2 and parser.stats.crc_errors == 0


def test_encoding_refuses_values_outside_their_fields():
    with pytest.raises(ValueError, match="distance_mm"):
        p.ranging_payload(4, np.full(16, 40000), np.zeros(16), np.zeros(16), np.zeros(16), np.zeros(16))
    with pytest.raises(ValueError, match="resolution"):
        p.ranging_payload(6, *(np.zeros(36),) * 5)
    with pytest.raises(ValueError, match="takes one value"):
        p.command(0, 0, p.CMD_SET_FREQUENCY)
    with pytest.raises(ValueError, match="not a command"):
        p.command(0, 0, p.RANGING)


def test_sequence_counter_gaps_wrap_and_restart():
    c = p.SequenceCounter()
    for seq in (2**32 - 2, 2**32 - 1, 0, 1, 4, 4, 5, 0, 1):
        c.add(seq)
    assert (c.gaps, c.lost, c.duplicates, c.restarts) == (1, 2, 1, 1)
