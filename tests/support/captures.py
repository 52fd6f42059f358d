"""Tiny capture files made in tests."""

from __future__ import annotations

import binascii
import struct
from collections.abc import Callable
from pathlib import Path

from pyrtcm.rtcmhelpers import calc_crc24q

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from drivers.rtcm import message_number
from drivers.ubx import fletcher8


def ubx_poll_capture(path: Path) -> Path:
    """A capture of one valid UBX frame (a NAV-PVT poll, empty payload): readable and
    recognisable, so that checks after the source are reached."""
    body = b"\x01\x07\x00\x00"
    path.write_bytes(b"\xb5\x62" + body + fletcher8(body))
    return path


def edit_rtcm_field(
    src: Path, out: Path, number: int, start: int, length: int, new: Callable[[int], int]
) -> int:
    """Write to ``out`` a copy of the RTCM3 capture ``src`` whose every message ``number``
    has the field of ``length`` bits at payload bit ``start`` set to ``new(old)`` (modulo
    2**length), its CRC-24Q made again by pyrtcm (a damage the frame's check cannot see);
    every other byte as it was. Returns how many messages were changed."""
    data = src.read_bytes()
    framer = Framer(PROTOCOLS)
    frames = [f for f in framer.feed(data) + framer.flush() if f.protocol == "rtcm"]
    parts, prev, n = [], 0, 0
    mask = (1 << length) - 1
    for f in frames:
        frame = bytearray(f.raw)
        if message_number(f.raw) == number:
            size = len(frame)
            bits = int.from_bytes(frame[3:-3], "big")
            shift = 8 * (size - 6) - start - length
            value = new((bits >> shift) & mask) & mask
            bits = bits & ~(mask << shift) | value << shift
            frame[3:-3] = bits.to_bytes(size - 6, "big")
            frame[-3:] = calc_crc24q(bytes(frame[:-3])).to_bytes(3, "big")
            n += 1
        parts += [data[prev : f.offset], bytes(frame)]
        prev = f.offset + len(f.raw)
    out.write_bytes(b"".join(parts) + data[prev:])
    return n


def edit_sbf_field(
    src: Path,
    out: Path,
    number: int,
    offset: int,
    fmt: str,
    new: Callable[[float], float],
    only: Callable[[bytes], bool] | None = None,
) -> int:
    """Write to ``out`` a copy of the SBF capture ``src`` whose blocks ``number`` (ID bits
    0-12; those ``only(block)`` accepts, if given) have the field packed as ``fmt`` (struct,
    little-endian) at byte ``offset`` of the block set to ``new(old)``, the block's CRC
    (CRC-16-CCITT over ID, Length and body) made again: a damage the check cannot see; every
    other byte as it was. Blocks found by the project's Framer. Returns how many blocks were
    changed (``new(old) != old``)."""
    data = bytearray(src.read_bytes())
    framer = Framer(PROTOCOLS)
    n = 0
    for f in framer.feed(bytes(data)) + framer.flush():
        i = f.offset
        if f.protocol != "sbf" or struct.unpack_from("<H", data, i + 4)[0] & 0x1FFF != number:
            continue
        if only is not None and not only(f.raw):
            continue
        old = struct.unpack_from(fmt, data, i + offset)[0]
        value = new(old)
        if value == old:
            continue
        struct.pack_into(fmt, data, i + offset, value)
        end = i + len(f.raw)
        struct.pack_into("<H", data, i + 2, binascii.crc_hqx(bytes(data[i + 4 : end]), 0))
        n += 1
    out.write_bytes(bytes(data))
    return n
