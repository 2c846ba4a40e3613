"""Wire protocol: framing, CRCs, resynchronisation, and a parser fuzzed with random and mutated frames."""
import binascii
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skinsafe.hardware import protocol as P


def _frames(n=6, stream=True):
    """Some command frames and a run of equal-size stream frames (which takes the parser's fast path)."""
    rng = np.random.default_rng(1)
    out = [P.encode_frame(P.IDENTIFY, 1, 0), P.encode_frame(P.CONFIG_CHUNK, 2, 7, bytes(range(200)))]
    if stream:
        for k in range(n):
            payload = P.STREAM_HEAD.pack(k * 1000, k, 64, 0) + rng.integers(0, 4096, 64, dtype=np.uint16).tobytes()
            out.append(P.encode_frame(P.STREAM_DATA, k, 0x5C1A0000, payload))
    out.append(P.encode_frame(P.IDENTIFY | P.RESPONSE, 3, 0x5C1A0000, b"\x00" + b"\xa5\x5a" * 10))
    return out


def test_frame_layout_and_crcs():
    f = P.encode_frame(P.CONFIG_CHUNK, 0x1234, 0x5C1A0001, b"abc")
    assert len(f) == P.OVERHEAD + 3 == 25
    assert f[:2] == b"\xa5\x5a" and f[2] == P.PROTOCOL_VERSION and f[3] == P.CONFIG_CHUNK
    assert f[4:6] == b"\x34\x12" and int.from_bytes(f[6:14], "little") == 0x5C1A0001
    assert f[14:16] == b"\x03\x00"
    assert int.from_bytes(f[16:18], "little") == binascii.crc_hqx(f[:16], 0xFFFF)
    assert P.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value
    assert int.from_bytes(f[-4:], "little") == zlib.crc32(f[:-4])
    assert zlib.crc32(b"123456789") == 0xCBF43926  # CRC-32 (ISO-HDLC) check value
    with pytest.raises(ValueError, match="exceeds"):
        P.encode_frame(P.CONFIG_CHUNK, 0, 0, bytes(P.MAX_PAYLOAD + 1))


def test_parser_byte_by_byte_with_garbage_between():
    frames = _frames()
    wire = b"\x00\xa5garbage\xa5" + b"\xa5\x5a\x01".join(frames) + b"\xa5"
    p = P.FrameParser()
    got = [f for b in wire for f in p.feed(bytes([b]))]
    assert [P.encode_frame(f.type, f.seq, f.uid, f.payload) for f in got] == frames
    assert p.crc_errors == 0
    assert p.bytes_skipped == 10 + 3 * (len(frames) - 1)  # the garbage, not the trailing half sync word
    whole = P.FrameParser().feed(wire)
    assert whole == got
    runs = P.FrameParser(runs=True)
    items = runs.feed(wire)
    assert P.expand(items) == got and runs.frames == len(got)
    items = P.FrameParser(runs=True).feed(b"".join(frames))  # back to back: the stream frames form a run
    assert [type(x).__name__ for x in items] == ["Frame"] * 3 + ["FrameRun", "Frame"]
    assert P.expand(items) == got and items[3].seqs.tolist() == [1, 2, 3, 4, 5]


def test_damaged_frames_are_dropped_and_the_rest_recovered():
    frames = _frames()
    wire = bytearray(b"".join(frames))
    at = len(frames[0]) + len(frames[1]) + len(frames[2]) + 30  # inside stream frame 1's payload
    wire[at] ^= 0x10
    hdr = len(frames[0]) + len(frames[1]) + len(frames[2]) + len(frames[3]) + 14  # frame 2's length
    wire[hdr] ^= 0x01
    p = P.FrameParser()
    got = p.feed(bytes(wire))
    assert [f.seq for f in got if f.type == P.STREAM_DATA] == [0, 3, 4, 5] and len(got) == len(frames) - 2
    assert p.crc_errors == 1


@settings(max_examples=150, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=3000), st.integers(1, 700))
def test_fuzz_random_bytes_never_crash(data, step):
    p = P.FrameParser()
    for i in range(0, len(data), step):
        for f in p.feed(data[i:i + step]):
            assert len(f.payload) <= P.MAX_PAYLOAD
    assert len(p.buf) <= max(P.OVERHEAD + P.MAX_PAYLOAD, 1)


@settings(max_examples=200, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(["flip", "drop", "insert"]), st.integers(0, 10**6), st.integers(0, 255)),
                max_size=8),
       st.integers(1, 500))
def test_fuzz_mutated_frames_recover_every_untouched_frame(mutations, step):
    frames = _frames(8)
    spans, pos = [], 0
    for f in frames:
        spans.append((pos, pos + len(f)))
        pos += len(f)
    wire = bytearray(b"".join(frames))
    touched = set()
    order = {"flip": 0, "insert": 1, "drop": 2}  # back to front; at one offset, drop last so it hits that byte
    muts = {(k, w % pos, 0 if k == "drop" else v) for k, w, v in mutations}  # one drop per offset
    for kind, i, value in sorted(muts, key=lambda m: (-m[1], order[m[0]], m[2])):
        touched |= {k for k, (a, b) in enumerate(spans) if (a < i if kind == "insert" else a <= i) and i < b}
        if kind == "flip":
            wire[i] ^= 1 << (value % 8)
        elif kind == "drop":
            del wire[i]
        else:
            wire[i:i] = bytes([value])
    p, pr = P.FrameParser(), P.FrameParser(runs=True)
    got = [f for i in range(0, len(wire), step) for f in p.feed(bytes(wire[i:i + step]))]
    assert P.expand([x for i in range(0, len(wire), step) for x in pr.feed(bytes(wire[i:i + step]))]) == got
    assert (pr.frames, pr.crc_errors, pr.bytes_skipped) == (p.frames, p.crc_errors, p.bytes_skipped)
    encoded = [P.encode_frame(f.type, f.seq, f.uid, f.payload) for f in got]
    assert all(e in frames for e in encoded)  # nothing invented
    for k, f in enumerate(frames):
        if k not in touched:
            assert f in encoded, f"untouched frame {k} was lost"


def test_a_lying_length_header_cannot_hold_frames_back():
    """A header with a valid CRC claiming 60,000 payload bytes: bounded by what the board can send,
    the parser drops it at once and the good frames behind it come out in the same read."""
    head = P.HEADER.pack(P.SYNC, P.PROTOCOL_VERSION, P.STREAM_DATA, 1, 7, 60000)
    liar = head + P.HEADER_CRC.pack(P.crc16(head))
    good = [P.encode_frame(P.STREAM_DATA, k, 7, P.STREAM_HEAD.pack(0, k, 32, 0) + bytes(64)) for k in range(3)]
    wire = liar + b"".join(good)
    bounded = P.FrameParser(P.board_max_payload(64, 32))
    assert [f.seq for f in bounded.feed(wire)] == [0, 1, 2] and bounded.resyncs == 1
    unbounded = P.FrameParser()
    assert unbounded.feed(wire) == []  # waits for 60,004 more bytes before it can resynchronise
    assert P.board_max_payload(64, 32) == P.MAX_SHORT_PAYLOAD and P.board_max_payload(4096, 32) == 4101
