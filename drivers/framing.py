"""Incremental framer for mixed UBX / RTCM3 / NMEA byte streams, plus shared driver state.

Frame formats (protocol definitions as data in :data:`FRAME_SPECS`, interpreted by
:meth:`Framer._try_binary`):

- UBX (u-blox Interface Description, "UBX frame structure"): ``B5 62 class id len(u16 LE)
  payload ck_a ck_b``, 8-bit Fletcher checksum over class..payload.
- RTCM3 (RTCM 10403.3 section 4, "Transport layer"): ``D3``, 6 reserved zero bits, 10-bit
  length, payload, CRC-24Q over header and payload.
- NMEA 0183: ``$`` + printable text + ``*hh`` + CR LF (XOR checksum).
- gpsd regression-log comments: a ``#`` at the start of a line up to the newline.

The framer never blocks and never trusts a claimed length: lengths are bounded, and after a
failed checksum it advances one byte, not the claimed length, so a false header cannot
swallow the valid frames that follow it. Memory is bounded by the longest allowed frame.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from dataclasses import dataclass
from functools import reduce
from operator import xor
from typing import Literal

import numpy as np

from service.core.timebase import diff_s, normalize
from service.core.types import Ephemeris, KlobucharParams, MeasurementEpoch, NavSubframe

log = logging.getLogger(__name__)

Protocol = Literal["ubx", "rtcm", "nmea"]
Event = MeasurementEpoch | NavSubframe | Ephemeris | KlobucharParams
"""What drivers emit: the event types of :mod:`service.core.types`."""

UBX_SYNC = b"\xb5\x62"
RTCM_PREAMBLE = 0xD3
DEFAULT_MAX_UBX_PAYLOAD = 8192
RTCM_MAX_PAYLOAD = 1023
DEFAULT_MAX_NMEA = 1024
DEFAULT_MAX_COMMENT = 8192


class Counters(Counter[str]):
    """Event and error counts of one stream, by name (exported in ZMQ ``STATUS``).

    Framing keys: ``bytes_in``, ``frames_ubx``, ``frames_rtcm``, ``frames_nmea``,
    ``comment_lines``, ``comment_bytes``, ``bytes_skipped``, ``resyncs``,
    ``bad_checksum_ubx``/``_rtcm``/``_nmea``, ``bad_length_ubx``/``_rtcm``.
    Decoding keys are documented in :mod:`drivers.ubx`, :mod:`drivers.rtcm` and
    :mod:`drivers.source`.
    """

    def as_dict(self) -> dict[str, int]:
        """Plain, key-sorted dict (for JSON)."""
        return {k: int(v) for k, v in sorted(self.items())}


@dataclass(frozen=True, slots=True)
class Frame:
    """One complete, checksum-valid frame and its byte offset in the stream."""

    protocol: Protocol
    raw: bytes
    offset: int


def _crc24q_table() -> tuple[int, ...]:
    poly = 0x1864CFB
    table = []
    for i in range(256):
        crc = i << 16
        for _ in range(8):
            crc <<= 1
            if crc & 0x1000000:
                crc ^= poly
        table.append(crc & 0xFFFFFF)
    return tuple(table)


_CRC24Q = _crc24q_table()


def crc24q(data: bytes | bytearray | memoryview) -> int:
    """CRC-24Q (Qualcomm) of ``data``, as used by RTCM3 (RTCM 10403.3 section 4.2)."""
    crc = 0
    for octet in bytes(data):
        crc = ((crc << 8) & 0xFFFFFF) ^ _CRC24Q[(crc >> 16) ^ octet]
    return crc


def fletcher8(data: bytes | bytearray | memoryview) -> bytes:
    """UBX 8-bit Fletcher checksum ``(ck_a, ck_b)`` of class..payload."""
    arr = np.frombuffer(bytes(data), dtype=np.uint8).astype(np.int64)
    n = arr.size
    ck_a = int(arr.sum()) & 0xFF
    ck_b = int(np.dot(arr, np.arange(n, 0, -1, dtype=np.int64))) & 0xFF
    return bytes((ck_a, ck_b))


def nmea_checksum_ok(body: bytes, hexsum: bytes) -> bool:
    """XOR of the bytes between ``$`` and ``*`` equals the two hex digits."""
    return reduce(xor, body, 0) == int(hexsum, 16)


# NMEA: address (2+ upper-case letters), then printable bytes except '$' and '*'.
_NMEA_BODY = rb"[A-Z]{2}[\x20-\x23\x25-\x29\x2b-\x7e]{0,%d}"
_PRINTABLE = rb"[\t\r\x20-\x7e]"


@dataclass(frozen=True, slots=True)
class _Spec:
    """A binary frame layout: sync bytes, header size, length field, trailer."""

    protocol: Protocol
    header_len: int
    trailer_len: int

    def payload_len(self, header: bytes) -> int | None:
        """Payload length from a complete header, or None if the header is impossible."""
        if self.protocol == "ubx":
            return header[4] | (header[5] << 8)
        if header[1] & 0xFC:  # RTCM3 reserved bits must be zero
            return None
        return ((header[1] & 0x03) << 8) | header[2]

    def check(self, frame: bytes, n_payload: int) -> bool:
        h = self.header_len
        if self.protocol == "ubx":
            return fletcher8(frame[2 : h + n_payload]) == frame[h + n_payload :]
        return crc24q(frame[: h + n_payload]) == int.from_bytes(frame[h + n_payload :], "big")


FRAME_SPECS: dict[int, _Spec] = {
    0xB5: _Spec("ubx", header_len=6, trailer_len=2),
    RTCM_PREAMBLE: _Spec("rtcm", header_len=3, trailer_len=3),
}

_NEED_MORE = -1
_NOT_A_FRAME = 0


class Framer:
    """Finds UBX, RTCM3 and NMEA frames in an arbitrary byte stream; ``feed`` never blocks.

    ``feed(data)`` returns the frames completed by ``data``; a frame split across feeds is
    returned once complete. ``flush()`` (at end of stream) resolves bytes still held for an
    incomplete candidate, so frames hidden behind a false header are not lost.
    """

    def __init__(
        self,
        counters: Counters | None = None,
        *,
        max_ubx_payload: int = DEFAULT_MAX_UBX_PAYLOAD,
        max_nmea: int = DEFAULT_MAX_NMEA,
        max_comment: int = DEFAULT_MAX_COMMENT,
    ) -> None:
        self.counters = counters if counters is not None else Counters()
        self.max_ubx_payload = max_ubx_payload
        self.max_nmea = max_nmea
        self.max_comment = max_comment
        self._buf = bytearray()
        self._offset = 0  # stream offset of self._buf[0]
        self._prev = 0x0A  # byte before self._buf[0]; stream start counts as a line start
        self._skipping = False
        body = _NMEA_BODY % (max_nmea,)
        self._nmea_re = re.compile(rb"\$(" + body + rb")\*([0-9A-Fa-f]{2})\r?\n")
        self._nmea_prefix_re = re.compile(
            rb"\$(?:[A-Z](?:[A-Z][\x20-\x23\x25-\x29\x2b-\x7e]*"
            rb"(?:\*(?:[0-9A-Fa-f](?:[0-9A-Fa-f]\r?)?)?)?)?)?"
        )
        self._comment_re = re.compile(rb"#" + _PRINTABLE + rb"*\n")
        self._comment_prefix_re = re.compile(rb"#" + _PRINTABLE + rb"*")

    @property
    def buffered(self) -> int:
        """Bytes held for an incomplete candidate frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; return the frames they complete, in stream order."""
        if data:
            self.counters["bytes_in"] += len(data)
            self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[Frame]:
        """End of stream: decide every held byte (incomplete candidates become garbage)."""
        frames = self._scan(final=True)
        if self._buf:  # cannot happen: final scans consume everything
            self._skip(len(self._buf))
            self._consume(len(self._buf))
        return frames

    # --- scanning ----------------------------------------------------------------------------
    def _scan(self, *, final: bool) -> list[Frame]:
        frames: list[Frame] = []
        buf = self._buf
        pos = 0
        n = len(buf)
        while pos < n:
            b = buf[pos]
            if b in FRAME_SPECS:
                size = self._try_binary(FRAME_SPECS[b], pos)
            elif b == 0x24:  # '$'
                size = self._try_nmea(pos)
            elif b == 0x23 and (buf[pos - 1] if pos else self._prev) == 0x0A:  # '#' at BOL
                size = self._try_comment(pos)
                if size > 0:
                    self.counters["comment_lines"] += 1
                    self.counters["comment_bytes"] += size
                    self._skipping = False
                    pos += size
                    continue
            else:
                size = _NOT_A_FRAME
            if size == _NEED_MORE and not final:
                break
            if size > 0:
                proto = FRAME_SPECS[b].protocol if b in FRAME_SPECS else "nmea"
                frames.append(Frame(proto, bytes(buf[pos : pos + size]), self._offset + pos))
                self.counters[f"frames_{proto}"] += 1
                self._skipping = False
                pos += size
                continue
            # not a frame here (or an incomplete candidate at end of stream): skip one byte
            self._skip(1)
            pos += 1
        self._consume(pos)
        return frames

    def _skip(self, count: int) -> None:
        if not self._skipping:
            self.counters["resyncs"] += 1
            self._skipping = True
        self.counters["bytes_skipped"] += count

    def _consume(self, count: int) -> None:
        if count:
            self._prev = self._buf[count - 1]
            del self._buf[:count]
            self._offset += count

    def _try_binary(self, spec: _Spec, pos: int) -> int:
        buf = self._buf
        avail = len(buf) - pos
        if spec.protocol == "ubx" and avail >= 2 and buf[pos + 1] != UBX_SYNC[1]:
            return _NOT_A_FRAME
        if avail < spec.header_len:
            return _NEED_MORE
        header = bytes(buf[pos : pos + spec.header_len])
        n_payload = spec.payload_len(header)
        limit = self.max_ubx_payload if spec.protocol == "ubx" else RTCM_MAX_PAYLOAD
        if n_payload is None or n_payload > limit or (spec.protocol == "rtcm" and n_payload == 0):
            self.counters[f"bad_length_{spec.protocol}"] += 1
            return _NOT_A_FRAME
        size = spec.header_len + n_payload + spec.trailer_len
        if avail < size:
            return _NEED_MORE
        if spec.check(bytes(buf[pos : pos + size]), n_payload):
            return size
        self.counters[f"bad_checksum_{spec.protocol}"] += 1
        log.debug("%s checksum failure at stream offset %d", spec.protocol, self._offset + pos)
        return _NOT_A_FRAME

    def _try_nmea(self, pos: int) -> int:
        end = min(len(self._buf), pos + self.max_nmea + 8)
        window = bytes(self._buf[pos:end])
        m = self._nmea_re.match(window)
        if m is not None:
            if nmea_checksum_ok(m.group(1), m.group(2)):
                return m.end()
            self.counters["bad_checksum_nmea"] += 1
            return _NOT_A_FRAME
        p = self._nmea_prefix_re.match(window)
        at_end = p is not None and p.end() == len(window) == len(self._buf) - pos
        if at_end and len(window) < self.max_nmea + 8:
            return _NEED_MORE
        return _NOT_A_FRAME

    def _try_comment(self, pos: int) -> int:
        end = min(len(self._buf), pos + self.max_comment)
        window = bytes(self._buf[pos:end])
        m = self._comment_re.match(window)
        if m is None:
            p = self._comment_prefix_re.match(window)
            at_end = p is not None and p.end() == len(window) == len(self._buf) - pos
            if at_end and len(window) < self.max_comment:
                return _NEED_MORE
            return _NOT_A_FRAME
        line = window[: m.end()]
        # A valid NMEA sentence inside the line ends the comment before its '$'.
        start = line.find(b"$", 1)
        while start > 0:
            s = self._nmea_re.match(line, start)
            if s is not None and s.end() == len(line) and nmea_checksum_ok(s.group(1), s.group(2)):
                return start
            start = line.find(b"$", start + 1)
        return m.end()


class WeekContext:
    """The GPS week for messages that carry only a time of week (RTCM MSM, UBX MEASX).

    Exact sources (UBX RXM-RAWX, NAV-TIMEGPS) set it; approximate ones (RTCM 1042 toe week,
    a constructor hint) only seed it. A time of week is resolved to the week (of the
    reference week and its neighbours) that puts it nearest the last known time, which also
    carries the week across a rollover.
    """

    def __init__(self, gps_week: int | None = None) -> None:
        self._ref: tuple[int, float | None] | None = None
        if gps_week is not None:
            self._ref = (gps_week, None)
        self.exact = False

    @property
    def known(self) -> bool:
        return self._ref is not None

    def set_exact(self, gps_week: int, tow_s: float) -> None:
        self._ref = normalize(gps_week, tow_s)
        self.exact = True

    def set_approx(self, gps_week: int, tow_s: float) -> None:
        if not self.exact:
            self._ref = normalize(gps_week, tow_s)

    def resolve(self, tow_s: float) -> int | None:
        """GPS week of a GPST time of week, or None when no week is known yet."""
        if self._ref is None:
            return None
        ref_week, ref_tow = self._ref
        if ref_tow is None:
            week = ref_week
        else:
            week = min(
                (ref_week - 1, ref_week, ref_week + 1),
                key=lambda w: abs(diff_s(w, tow_s, ref_week, ref_tow)),
            )
        self._ref = (week, tow_s)
        return week
