"""NMEA 0183 sentence framing; sentences are recognised and counted, not mapped.

Sentence structure (NMEA 0183 v4.11 / IEC 61162-1, "Sentences"): ``$``, an address of
upper-case letters, printable fields without ``$`` or ``*``, ``*hh`` (XOR of the bytes
between ``$`` and ``*``, two hex digits) and CR LF; a bare LF is taken too. The payload
bound applies to the text between ``$`` and ``*``.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from operator import xor

from drivers.framing import BAD_CHECKSUM, NEED_MORE, NOT_A_FRAME

DEFAULT_MAX_NMEA = 1024

# address (2+ upper-case letters), then printable bytes except '$' and '*'
_BODY = rb"[A-Z]{2}[\x20-\x23\x25-\x29\x2b-\x7e]{0,%d}"
# what a sentence can start with, to tell an incomplete sentence from garbage
_PREFIX = re.compile(
    rb"\$(?:[A-Z](?:[A-Z][\x20-\x23\x25-\x29\x2b-\x7e]*"
    rb"(?:\*(?:[0-9A-Fa-f](?:[0-9A-Fa-f]\r?)?)?)?)?)?"
)


def nmea_checksum_ok(body: bytes, hexsum: bytes) -> bool:
    """XOR of the bytes between ``$`` and ``*`` equals the two hex digits."""
    return functools.reduce(xor, body, 0) == int(hexsum, 16)


@functools.cache
def _sentence_re(max_body: int) -> re.Pattern[bytes]:
    return re.compile(rb"\$(" + _BODY % (max_body,) + rb")\*([0-9A-Fa-f]{2})\r?\n")


@dataclass(frozen=True, slots=True)
class SentenceFraming:
    """``$ ... *hh CR LF`` sentences (see the module docstring)."""

    sync: bytes = b"$"
    max_payload: int = DEFAULT_MAX_NMEA

    def measure(self, buf: bytes | bytearray, pos: int, max_payload: int) -> int:
        """See :meth:`drivers.framing.Framing.measure`."""
        end = min(len(buf), pos + max_payload + 8)
        window = bytes(buf[pos:end])
        m = _sentence_re(max_payload).match(window)
        if m is not None:
            return m.end() if nmea_checksum_ok(m.group(1), m.group(2)) else BAD_CHECKSUM
        p = _PREFIX.match(window)
        at_end = p is not None and p.end() == len(window) == len(buf) - pos
        if at_end and len(window) < max_payload + 8:
            return NEED_MORE
        return NOT_A_FRAME


FRAMING = SentenceFraming()
