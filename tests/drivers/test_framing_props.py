"""Property tests (hypothesis) for the framer and the stream decoder.

Valid frames come from real captures (read by pyubx2's own stream reader) and from
generated frames sealed with the libraries' checksum helpers (pyubx2 Fletcher, pyrtcm
CRC-24Q) or a plain XOR for NMEA, never with the code under test.
"""

from __future__ import annotations

import functools
from functools import reduce
from operator import xor

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyrtcm.rtcmhelpers import calc_crc24q
from pyubx2 import UBXReader
from pyubx2.ubxhelpers import calc_checksum

from drivers import ubx
from drivers.framing import BinaryFraming, Framer
from drivers.protocols import PROTOCOLS
from drivers.source import StreamDecoder
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    ReceiverFix,
)
from tests.support.paths import DATA

TINY = DATA / "tiny-ubx-rtcm"
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@functools.cache
def real_frames() -> tuple[bytes, ...]:
    out: list[bytes] = []
    for name in ("pygpsdata-RXMRAWX.log", "pygpsdata-RTCM3.log", "pygpsdata-NTRIP-USCL00CHL0.log"):
        with open(TINY / name, "rb") as s:
            out += [raw for raw, _ in UBXReader(s, protfilter=7, quitonerror=0)]
    return tuple(out)


def ubx_frame(cls: int, mid: int, payload: bytes) -> bytes:
    body = bytes([cls, mid]) + len(payload).to_bytes(2, "little") + payload
    return b"\xb5\x62" + body + calc_checksum(body)


def rtcm_frame(payload: bytes) -> bytes:
    body = b"\xd3" + len(payload).to_bytes(2, "big") + payload
    return body + calc_crc24q(body).to_bytes(3, "big")


def nmea_frame(body: str) -> bytes:
    raw = body.encode()
    return b"$" + raw + b"*" + f"{reduce(xor, raw, 0):02X}".encode() + b"\r\n"


ubx_frames = st.builds(ubx_frame, st.integers(0, 255), st.integers(0, 255), st.binary(max_size=300))
rtcm_frames = st.builds(rtcm_frame, st.binary(min_size=1, max_size=300))
nmea_bodies = st.builds(
    lambda talker, rest: talker + rest,
    st.sampled_from(["GPGGA", "GNRMC", "GBGSV", "PUBX"]),
    st.text(alphabet="ABCDEFXYZ0123456789,.-", max_size=70),
)
nmea_frames = st.builds(nmea_frame, nmea_bodies)
valid_frames = st.one_of(st.sampled_from(real_frames()), ubx_frames, rtcm_frames, nmea_frames)

printable = st.binary(max_size=40).map(lambda b: bytes(32 + (x % 95) for x in b))
garbage = st.one_of(
    st.binary(max_size=64),
    # false headers claiming lengths up to the caps and beyond
    st.builds(lambda b: b"\xb5\x62" + b, st.binary(min_size=0, max_size=8)),
    st.builds(lambda b: b"\xd3" + b, st.binary(min_size=0, max_size=5)),
    # unfinished NMEA and gpsd comment lines
    st.builds(lambda b: b"$GP" + b, printable),
    st.builds(lambda b: b"\n#" + b, printable),
    st.builds(lambda a, b: b"\n#" + a + b"$" + b, printable, printable),
)


@st.composite
def mixed_streams(draw) -> tuple[bytes, list[tuple[int, bytes]]]:
    """Valid frames with garbage between them; returns the bytes and (offset, frame)."""
    parts: list[bytes] = []
    placed: list[tuple[int, bytes]] = []
    pos = 0
    for _ in range(draw(st.integers(1, 8))):
        g = draw(garbage)
        parts.append(g)
        pos += len(g)
        f = draw(valid_frames)
        placed.append((pos, f))
        parts.append(f)
        pos += len(f)
    tail = draw(garbage)
    parts.append(tail)
    return b"".join(parts), placed


def split_feed(framer: Framer, data: bytes, cuts: list[int]) -> list:
    out = []
    prev = 0
    for cut in [*sorted({min(c, len(data)) for c in cuts}), len(data)]:
        out += framer.feed(data[prev:cut])
        prev = cut
    return out + framer.flush()


@SETTINGS
@given(mixed_streams())
def test_garbage_never_loses_a_valid_frame(stream):
    data, placed = stream
    framer = Framer(PROTOCOLS)
    found = {(f.offset, f.raw) for f in framer.feed(data) + framer.flush()}
    for offset, raw in placed:
        assert (offset, raw) in found
    assert framer.buffered == 0


@SETTINGS
@given(mixed_streams(), st.lists(st.integers(0, 5000), max_size=30))
def test_split_anywhere_equals_one_shot(stream, cuts):
    data, _ = stream
    one = Framer(PROTOCOLS)
    whole = [(f.protocol, f.offset, f.raw) for f in one.feed(data) + one.flush()]
    many = Framer(PROTOCOLS)
    parts = [(f.protocol, f.offset, f.raw) for f in split_feed(many, data, cuts)]
    assert parts == whole
    assert many.counters == one.counters


@SETTINGS
@given(st.lists(st.binary(max_size=3000), max_size=12))
def test_each_feed_returns_with_bounded_memory(chunks):
    framer = Framer(PROTOCOLS)
    longest = max(framer.max_payload.values()) + 8  # + header and trailer
    limit = max(longest, framer.max_comment)
    frames = []
    for chunk in chunks:
        got = framer.feed(chunk)
        assert isinstance(got, list)
        frames += got
        assert framer.buffered <= limit
    frames += framer.flush()
    c = framer.counters
    # every byte is a frame byte, a comment byte or a counted skipped byte
    framed = sum(len(f.raw) for f in frames)
    assert (
        framed + c["comment_bytes"] + c["bytes_skipped"] == c["bytes_in"] == sum(map(len, chunks))
    )


# Frames with valid checksums but random content under the message types the mappers read.
used_ubx = st.builds(
    ubx_frame,
    st.just(0x02) | st.just(0x01),
    st.sampled_from([0x15, 0x14, 0x13, 0x07, 0x20]),
    st.binary(max_size=200),
)


def numbered(number: int, rest: bytes) -> bytes:
    head = (number << 4 | (rest[0] >> 4 if rest else 0)).to_bytes(2, "big")
    return rtcm_frame(head + rest[1:])


used_rtcm = st.builds(
    numbered, st.sampled_from([1042, 1124, 1125, 1126, 1127, 1077, 1019]), st.binary(max_size=120)
)
EVENT_TYPES = (MeasurementEpoch, NavSubframe, Ephemeris, KlobucharParams, ReceiverFix)


@SETTINGS
@given(
    st.lists(st.one_of(used_ubx, used_rtcm, valid_frames, garbage), max_size=12), st.integers(1, 64)
)
def test_decoder_survives_checksum_valid_nonsense(items, chunk):
    dec = StreamDecoder(gps_week=2300)
    data = b"".join(items)
    events = []
    for i in range(0, len(data), chunk):
        events += dec.feed(data[i : i + chunk])
    events += dec.flush()
    assert all(isinstance(e, EVENT_TYPES) for e in events)
    for e in events:
        if isinstance(e, MeasurementEpoch):
            assert len(e.pr_m) == len(e.frac_pr_m) == len(e.prn)


@SETTINGS
@given(mixed_streams(), st.integers(0, 255), st.integers(0, 255), st.integers(0, 400))
def test_ubx_measure_equals_the_generic_binary_framing(stream, flip_at, flip_bits, max_payload):
    """drivers.ubx.UbxFraming measures in place what the generic BinaryFraming.measure
    (sync, the length from ``payload_len``, ``check`` over a copy) measures from the same
    layout, at every offset of streams of valid, damaged and false frames, and for any
    payload bound."""
    data, _ = stream
    if data:  # one damaged byte somewhere (a checksum, a length or a sync byte)
        k = flip_at % len(data)
        data = data[:k] + bytes([data[k] ^ flip_bits]) + data[k + 1 :]
    buf = bytearray(data)
    for pos in range(len(buf)):
        if buf[pos] != ubx.SYNC[0]:
            continue
        for limit in (max_payload, ubx.DEFAULT_MAX_PAYLOAD):
            for end in (len(buf), pos + 1 + (flip_at % max(1, len(buf) - pos))):
                view = buf[:end]
                got = ubx.FRAMING.measure(view, pos, limit)
                assert got == BinaryFraming.measure(ubx.FRAMING, view, pos, limit), (pos, limit)
