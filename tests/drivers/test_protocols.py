"""The protocol registry (:mod:`drivers.protocols`): a protocol given as one more entry is
framed, mapped and counted by the framer and the stream decoder with no other change."""

from __future__ import annotations

from functools import reduce
from operator import xor

import pytest

from drivers.framing import BinaryFraming, Framer, WeekContext
from drivers.protocols import PROTOCOLS, ProtocolSpec
from drivers.source import StreamDecoder
from drivers.ubx import fletcher8
from service.core.counters import Counters
from service.core.errors import DecodeError
from service.core.types import KlobucharParams


def toy_frame(payload: bytes) -> bytes:
    """``AA 44 length(u8) payload xor``: a made-up protocol for these tests."""
    body = bytes([len(payload)]) + payload
    return b"\xaa\x44" + body + bytes([reduce(xor, body, 0)])


class ToyMapper:
    """Eight payload bytes -> Klobuchar alpha (the first four, times ``scale``)."""

    def __init__(self, counters: Counters, week: WeekContext, *, scale: float = 1.0) -> None:
        self.counters = counters
        self.scale = scale

    def on_frame(self, raw: bytes) -> list[KlobucharParams]:
        payload = raw[3:-1]
        if len(payload) != 8:
            raise DecodeError(f"toy payload of {len(payload)} bytes")
        self.counters["toy_mapped"] += 1
        alpha = tuple(b * self.scale for b in payload[:4])
        return [KlobucharParams(alpha=alpha, beta=(0.0, 0.0, 0.0, 0.0))]

    def flush(self) -> list[KlobucharParams]:
        return []


TOY = ProtocolSpec(
    "toy",
    BinaryFraming(
        sync=b"\xaa\x44",
        header_len=3,
        trailer_len=1,
        payload_len=lambda header: header[2],
        check=lambda frame: reduce(xor, frame[2:-1], 0) == frame[-1],
        max_payload=64,
    ),
    ToyMapper,
)
NMEA = b"$GPGGA,,,,,,0,,,,,,,,*66\r\n"
NAV_EOE = b"\x01\x61\x04\x00" + bytes(4)
UBX = b"\xb5\x62" + NAV_EOE + fletcher8(NAV_EOE)
GOOD = toy_frame(bytes(range(1, 9)))
BAD_CHECK = GOOD[:-1] + bytes([GOOD[-1] ^ 1])
SHORT = toy_frame(b"\x01\x02")
STREAM = NMEA + b"\xaa\x00junk" + BAD_CHECK + GOOD + UBX + SHORT + GOOD


def _decode(dec: StreamDecoder, data: bytes) -> list:
    events = []
    for i in range(len(data)):  # one byte at a time: every frame is split
        events += dec.feed(data[i : i + 1])
    return events + dec.flush()


def test_registry_names_and_syncs_are_unique():
    assert len({p.name for p in PROTOCOLS}) == len(PROTOCOLS)
    assert len({bytes(p.framing.sync) for p in PROTOCOLS}) == len(PROTOCOLS)


def test_a_protocol_added_to_the_table_is_framed_mapped_and_counted():
    dec = StreamDecoder(protocols=(*PROTOCOLS, TOY), mapper_options={"toy": {"scale": 2.0}})
    events = _decode(dec, STREAM)
    alpha = (2.0, 4.0, 6.0, 8.0)
    assert events == [KlobucharParams(alpha=alpha, beta=(0.0,) * 4)] * 2
    c = dec.counters
    assert (c["frames_toy"], c["toy_mapped"], c["map_errors_toy"]) == (3, 2, 1)
    assert c["bad_checksum_toy"] == 1
    assert (c["frames_nmea"], c["nmea_ignored"]) == (1, 1)
    assert (c["frames_ubx"], c["ubx:NAV-EOE"], c["ubx_ignored"]) == (1, 1, 1)
    assert c["bytes_skipped"] == len(b"\xaa\x00junk") + len(BAD_CHECK)
    framed = len(STREAM) - c["bytes_skipped"]
    assert framed == len(NMEA) + len(UBX) + len(SHORT) + 2 * len(GOOD)


def test_without_the_entry_the_same_bytes_are_garbage():
    dec = StreamDecoder()
    assert _decode(dec, STREAM) == []
    c = dec.counters
    assert c["frames_toy"] == 0 and c["frames_nmea"] == 1 and c["frames_ubx"] == 1
    assert c["bytes_skipped"] == len(STREAM) - len(NMEA) - len(UBX)


def test_a_protocol_without_a_mapper_is_counted_as_ignored():
    quiet = ProtocolSpec("toy", TOY.framing, None)
    dec = StreamDecoder(protocols=(*PROTOCOLS, quiet))
    assert _decode(dec, GOOD + SHORT) == []
    assert dec.counters["frames_toy"] == dec.counters["toy_ignored"] == 2


def test_payload_bound_by_protocol_name():
    framer = Framer((*PROTOCOLS, TOY), max_payload={"toy": 4})
    frames = framer.feed(GOOD + SHORT) + framer.flush()
    assert [f.raw for f in frames] == [SHORT]
    assert framer.counters["bad_length_toy"] == 1


def test_conflicts_and_unknown_names_are_refused():
    clash = ProtocolSpec("clash", BinaryFraming(b"\xb5\x62", 3, 1, len, bool, 8), None)
    with pytest.raises(ValueError, match="same sync"):
        Framer((*PROTOCOLS, clash))
    with pytest.raises(ValueError, match="max_payload"):
        Framer(PROTOCOLS, max_payload={"toy": 4})
    with pytest.raises(ValueError, match="mapper_options"):
        StreamDecoder(mapper_options={"nmea": {}})


def test_a_protocol_sharing_a_first_byte_is_matched_by_its_sync():
    """A toy whose sync starts with UBX's first byte: both are framed, by sync pattern
    (as SBF ``$@`` and NMEA ``$``), and a bad toy frame is counted as the toy's."""
    framing = BinaryFraming(b"\xb5\x44", 3, 1, TOY.framing.payload_len, TOY.framing.check, 64)
    shared = ProtocolSpec("toy", framing, ToyMapper)
    good = b"\xb5" + GOOD[1:]
    bad = b"\xb5" + BAD_CHECK[1:]
    dec = StreamDecoder(protocols=(*PROTOCOLS, shared))
    events = _decode(dec, UBX + bad + good + NMEA + UBX)
    assert events == [KlobucharParams(alpha=(1.0, 2.0, 3.0, 4.0), beta=(0.0,) * 4)]
    c = dec.counters
    assert (c["frames_toy"], c["frames_ubx"], c["frames_nmea"]) == (1, 2, 1)
    assert (c["bad_checksum_toy"], c["bad_checksum_ubx"]) == (1, 0)
    assert c["bytes_skipped"] == len(bad)
