"""Unit tests of the Pixy v1 block protocol parser/encoder (pixy_driver.protocol, .arrival)."""

import random
import struct

from pixy_driver.arrival import ArrivalLog
from pixy_driver.protocol import (
    SYNC,
    SYNC_CC,
    ParserParams,
    PixyBlock,
    PixyParser,
    block_checksum,
    block_in_range,
    encode_block,
    encode_frame,
)
import pytest


def random_block(rng: random.Random, cc_probability: float = 0.0) -> tuple:
    """A random in-range block tuple (sig, x, y, w, h[, angle])."""
    x, y = rng.randint(0, 319), rng.randint(0, 199)
    w, h = rng.randint(1, 320), rng.randint(1, 200)
    if rng.random() < cc_probability:
        digits = rng.randint(2, 5)
        sig = 0
        for _ in range(digits):
            sig = sig * 8 + rng.randint(1, 7)
        return (sig, x, y, w, h, rng.randint(-180, 180))
    return (rng.randint(1, 7), x, y, w, h)


def random_frames(rng: random.Random, n_frames: int, max_blocks: int = 4,
                  cc_probability: float = 0.2) -> list[list[tuple]]:
    return [[random_block(rng, cc_probability) for _ in range(rng.randint(0, max_blocks))]
            for _ in range(n_frames)]


def as_tuples(frame) -> list[tuple]:
    """A parsed frame as encoder tuples, to compare with what was sent."""
    out = []
    for b, a in zip(frame.blocks, frame.angles_deg, strict=True):
        t = (b.signature, int(b.x_px), int(b.y_px), int(b.width_px), int(b.height_px))
        out.append(t if a is None else (*t, a))
    return out


def parse_all(stream: bytes, chunks: list[int] | None = None) -> tuple[list, PixyParser]:
    p = PixyParser()
    frames = []
    if chunks is None:
        frames += p.feed(stream)
    else:
        pos = 0
        for c in chunks:
            frames += p.feed(stream[pos:pos + c])
            pos += c
        frames += p.feed(stream[pos:])
    frames += p.flush()
    return frames, p


# ---------------------------------------------------------------------------- wire format
def test_wire_bytes_of_one_block_match_the_documented_layout():
    data = encode_frame([(1, 160, 100, 10, 8)])
    words = struct.unpack('<8H', data)
    # frame marker, block sync, checksum, sig, x, y, w, h: little-endian 16-bit words
    assert words == (SYNC, SYNC, 1 + 160 + 100 + 10 + 8, 1, 160, 100, 10, 8)
    assert data[:4] == b'\x55\xaa\x55\xaa'


def test_colour_code_block_layout_and_checksum_includes_angle():
    data = encode_frame([(0o12, 100, 50, 20, 10, -45)])
    words = struct.unpack('<9H', data)
    assert words[:2] == (SYNC, SYNC_CC)
    assert words[8] == (-45) & 0xFFFF
    assert words[2] == (0o12 + 100 + 50 + 20 + 10 + 0xFFD3) & 0xFFFF
    assert block_checksum(0o12, 100, 50, 20, 10, -45) == words[2]


def test_empty_frame_is_marker_plus_no_data():
    assert encode_frame([]) == b'\x55\xaa\x00\x00\x00\x00'
    frames, p = parse_all(encode_frame([]) * 3)
    assert [f.blocks for f in frames] == [(), (), ()]
    assert [f.closed_by for f in frames] == ['no_data'] * 3
    assert p.bytes_dropped == 0


def test_encoder_rejects_out_of_range_and_non_finite_blocks():
    with pytest.raises(ValueError, match='out of Pixy range'):
        encode_frame([(1, 320, 10, 5, 5)])
    with pytest.raises(ValueError, match='out of Pixy range'):
        encode_frame([(8, 10, 10, 5, 5)])  # 8 is not a normal signature
    with pytest.raises(ValueError, match='finite'):
        encode_frame([(1, float('nan'), 10, 5, 5)])


def test_encoder_accepts_block_objects_and_rounds_to_pixels():
    blk = PixyBlock(signature=3, x_px=10.4, y_px=20.6, width_px=4.0, height_px=5.0)
    frames, _ = parse_all(encode_frame([blk]))
    assert as_tuples(frames[0]) == [(3, 10, 21, 4, 5)]


# ---------------------------------------------------------------------------- round trip
def test_round_trip_many_random_frames():
    rng = random.Random(1)
    sent = random_frames(rng, 200)
    stream = b''.join(encode_frame(f) for f in sent)
    frames, p = parse_all(stream)
    assert [as_tuples(f) for f in frames] == sent
    assert p.checksum_errors == p.resyncs == p.bytes_dropped == p.out_of_range == 0
    assert p.frames == 200 and p.blocks == sum(len(f) for f in sent)
    assert [f.seq for f in frames] == list(range(200))


def test_split_at_every_byte_boundary_gives_same_frames():
    rng = random.Random(2)
    sent = random_frames(rng, 6, max_blocks=3, cc_probability=0.5)
    stream = b''.join(encode_frame(f) for f in sent)
    whole, _ = parse_all(stream)
    assert [as_tuples(f) for f in whole] == sent
    for k in range(len(stream) + 1):
        split, _ = parse_all(stream, [k])
        assert split == whole, k
    bytewise, _ = parse_all(stream, [1] * len(stream))
    assert bytewise == whole


def test_one_frame_latency_and_end_offset():
    a = encode_frame([(1, 100, 100, 5, 5)])
    b = encode_frame([(2, 50, 60, 7, 7)])
    p = PixyParser()
    assert p.feed(a) == []  # complete on the wire, but the parser cannot know yet
    assert p.open_frame_blocks == 1
    out = p.feed(b[:4])  # the next frame's double sync closes it
    assert len(out) == 1 and out[0].closed_by == 'next_frame'
    assert out[0].end_offset == len(a)
    assert p.feed(b[4:]) == []
    out = p.flush()
    assert out[0].end_offset == len(a) + len(b) and out[0].closed_by == 'flush'


def test_end_marker_closes_frame_without_latency():
    p = PixyParser()
    out = p.feed(encode_frame([(1, 100, 100, 5, 5)], end_marker=True))
    assert len(out) == 1 and out[0].closed_by == 'no_data'


def test_feed_datagram_emits_at_once_and_isolates_datagrams():
    p = PixyParser()
    out = p.feed_datagram(encode_frame([(1, 1, 2, 3, 4)]))
    assert [as_tuples(f) for f in out] == [[(1, 1, 2, 3, 4)]]
    # a truncated datagram loses its partial block, and does not leak into the next one
    trunc = encode_frame([(1, 5, 5, 5, 5), (2, 6, 6, 6, 6)])[:-3]
    out = p.feed_datagram(trunc)
    assert [as_tuples(f) for f in out] == [[(1, 5, 5, 5, 5)]]
    out = p.feed_datagram(encode_frame([(3, 7, 7, 7, 7)]))
    assert [as_tuples(f) for f in out] == [[(3, 7, 7, 7, 7)]]
    assert p.feed_datagram(encode_frame([]))[0].blocks == ()


def test_lone_frame_marker_is_an_empty_frame():
    # a frame marker without blocks followed by a normal frame: SYNC SYNC SYNC cs ...
    a = encode_frame([(1, 10, 10, 2, 2)])
    stream = a + b'\x55\xaa' + encode_frame([(2, 20, 20, 3, 3)])
    frames, _ = parse_all(stream)
    assert [as_tuples(f) for f in frames] == [[(1, 10, 10, 2, 2)], [], [(2, 20, 20, 3, 3)]]


# ---------------------------------------------------------------------------- blocks
def test_colour_code_blocks_round_trip_first_and_mixed():
    sent = [[(0o12, 100, 50, 20, 10, -45), (1, 3, 4, 5, 6), (0o77777, 319, 199, 320, 200, 180)],
            [(0o11, 0, 0, 1, 1, -180)]]
    frames, _ = parse_all(b''.join(encode_frame(f) for f in sent))
    assert [as_tuples(f) for f in frames] == sent
    assert frames[0].angles_deg == (-45, None, 180)


def test_sync_bytes_inside_a_block_body_do_not_split_it():
    # signature 0o52525 = 0x5555 and x = 170 = 0xaa: the body holds the bytes 55 aa
    blk = (0o52525, 170, 85, 170, 85, -86)
    data = encode_frame([blk, (1, 1, 1, 1, 1)])
    assert b'\x55\xaa' in data[4:]
    frames, _ = parse_all(data)
    assert [as_tuples(f) for f in frames] == [[blk, (1, 1, 1, 1, 1)]]


def test_many_blocks_per_frame_and_overflow_bound():
    rng = random.Random(3)
    big = [random_block(rng) for _ in range(135)]
    frames, p = parse_all(encode_frame(big) + encode_frame([(1, 1, 1, 1, 1)]))
    assert len(frames[0].blocks) == 130 and as_tuples(frames[0]) == big[:130]
    assert p.overflow_blocks == 5 and p.rejected['overflow'] == 5
    p2 = PixyParser(ParserParams(max_blocks_per_frame=135))
    out = p2.feed(encode_frame(big)) + p2.flush()
    assert as_tuples(out[0]) == big


def test_bad_checksum_block_dropped_and_counted_others_kept():
    good1, good2 = (1, 10, 20, 30, 40), (2, 11, 21, 31, 41)
    bad = encode_block(3, 50, 60, 7, 8, checksum=block_checksum(3, 50, 60, 7, 8) ^ 0x0100)
    stream = (b'\x55\xaa' + encode_block(*good1) + bad + encode_block(*good2)
              + encode_frame([(4, 1, 1, 1, 1)]))
    frames, p = parse_all(stream)
    assert [as_tuples(f) for f in frames] == [[good1, good2], [(4, 1, 1, 1, 1)]]
    assert p.checksum_errors == 1 and p.rejected['checksum'] == 1
    assert p.bytes_dropped == 12  # the rejected body


def test_out_of_range_fields_with_valid_checksum_are_rejected():
    bad_blocks = [(1, 320, 0, 1, 1), (1, 0, 200, 1, 1), (1, 0, 0, 0, 1), (1, 0, 0, 321, 1),
                  (1, 0, 0, 1, 201), (0, 5, 5, 1, 1), (9, 5, 5, 1, 1),
                  (0o10, 5, 5, 1, 1, 0), (0o12, 5, 5, 1, 1, 181), (0o123456, 5, 5, 1, 1, 0)]
    for blk in bad_blocks:
        assert not block_in_range(*blk), blk
    stream = b'\x55\xaa' + b''.join(encode_block(*b) for b in bad_blocks)
    stream += encode_block(1, 5, 5, 1, 1) + encode_frame([])
    frames, p = parse_all(stream)
    assert [as_tuples(f) for f in frames] == [[(1, 5, 5, 1, 1)], []]
    assert p.out_of_range == len(bad_blocks) and p.checksum_errors == 0


# ---------------------------------------------------------------------------- resync
def test_resync_after_reading_55aa_drops_exactly_one_byte():
    blk1, blk2 = (1, 10, 20, 30, 40), (2, 11, 21, 31, 41)
    # an extra 0xaa before the next sync: the word read there is bytes aa 55 = 0x55aa
    stream = b'\x55\xaa' + encode_block(*blk1) + b'\xaa' + encode_block(*blk2) + encode_frame([])
    frames, p = parse_all(stream)
    assert [as_tuples(f) for f in frames] == [[blk1, blk2], []]
    assert p.resyncs == 1 and p.bytes_dropped == 1 and p.checksum_errors == 0


def test_resync_after_odd_garbage_between_frames():
    rng = random.Random(4)
    sent = random_frames(rng, 10, cc_probability=0.3)
    parts = [encode_frame(f) for f in sent]
    stream = b''.join(parts[:5]) + b'\x13\x37\x42' + b''.join(parts[5:])
    frames, p = parse_all(stream)
    assert [as_tuples(f) for f in frames] == sent
    assert p.bytes_dropped == 3 and p.resyncs == 1


def test_a_lost_byte_costs_one_block_then_parser_recovers():
    rng = random.Random(5)
    sent = [[random_block(rng) for _ in range(3)] for _ in range(6)]
    parts = [encode_frame(f) for f in sent]
    damaged = bytearray(parts[2])
    del damaged[4 + 14 + 5]  # a byte inside the second block of frame 2
    frames, p = parse_all(b''.join(parts[:2]) + bytes(damaged) + b''.join(parts[3:]))
    got = [as_tuples(f) for f in frames]
    assert got[:2] == sent[:2] and got[3:] == sent[3:]
    assert got[2] == [sent[2][0], sent[2][2]]  # only the damaged block is lost
    assert p.checksum_errors == 1


def test_joining_a_stream_mid_frame():
    rng = random.Random(6)
    sent = random_frames(rng, 5, max_blocks=3)
    sent[0] = [random_block(rng) for _ in range(3)]
    stream = b''.join(encode_frame(f) for f in sent)
    frames, p = parse_all(stream[9:])  # cut inside the first block of frame 0
    assert [as_tuples(f) for f in frames] == sent[1:]
    assert p.orphan_blocks == 2 and p.bytes_dropped > 0


def test_garbage_is_bounded_in_memory_and_never_raises():
    rng = random.Random(7)
    p = PixyParser()
    for _ in range(200):
        p.feed(bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 600))))
        assert p.buffered_bytes <= 15
        assert p.open_frame_blocks <= 130
    assert p.feed(None) == [] and p.feed('55aa') == [] and p.feed(12) == []
    assert p.rejected['bad_input'] == 3


def test_parser_params_validation_names_the_field():
    with pytest.raises(ValueError, match='max_blocks_per_frame'):
        ParserParams(max_blocks_per_frame=0)
    with pytest.raises(ValueError, match='max_blocks_per_frame'):
        ParserParams(max_blocks_per_frame=2.5)


# ---------------------------------------------------------------------------- stamping
def test_arrival_log_stamps_frame_by_its_last_byte_not_by_the_closing_read():
    a = encode_frame([(1, 100, 100, 5, 5)])
    b = encode_frame([(2, 50, 60, 7, 7)])
    p, log = PixyParser(), ArrivalLog()
    total, stamps = 0, []
    # frame a arrives in two reads (t=1.00, 1.01); frame b 20 ms later (t=1.03) closes it
    for chunk, t in ((a[:7], 1.00), (a[7:], 1.01), (b, 1.03)):
        frames = p.feed(chunk)
        total += len(chunk)
        log.record(total, t)
        stamps += [log.time_of(f.end_offset) for f in frames]
    assert stamps == [1.01]
    assert log.time_of(0) == 1.00 and log.time_of(10**9) == 1.03


def test_arrival_log_rejects_bad_input_and_is_bounded():
    log = ArrivalLog(capacity=4)
    assert log.time_of(5) is None
    log.record(10, 1.0)
    log.record(20, float('nan'))
    log.record(5, 2.0)
    log.record(30, 0.5)
    assert log.rejected == {'nan': 1, 'out_of_order': 2}
    for i in range(10):
        log.record(40 + i, 3.0 + i)
    assert log.time_of(0) == 9.0  # fell out of the log: oldest kept
    with pytest.raises(ValueError, match='capacity'):
        ArrivalLog(capacity=0)
