"""The protocol registry: one entry per stream protocol, read by the framer and the decoder.

An entry names the protocol (the ``Frame.protocol`` of its frames and the suffix of its
counter keys: ``frames_<name>``, ``bad_checksum_<name>``, ...), gives its framing (how a
frame is found: sync, length, check) and the factory of its mapper (frames to events).
Adding a protocol is one module that defines both, plus one line here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from drivers import nmea, rtcm, sbf, ubx
from drivers.framing import Event, Framing


class Mapper(Protocol):
    """Turns the checksum-valid frames of one protocol, in stream order, into events."""

    def on_frame(self, raw: bytes) -> list[Event]:
        """Events completed by one frame; raises DecodeError on unexpected content and
        lets library parse errors through (the stream decoder counts both)."""
        ...

    def flush(self) -> list[Event]:
        """Events still pending (end of stream or idle line)."""
        ...


MapperFactory = Callable[..., Mapper]
"""Called as ``factory(counters, week, **options)`` with the stream's
:class:`~service.core.counters.Counters` and :class:`~drivers.framing.WeekContext`."""


@dataclass(frozen=True, slots=True)
class ProtocolSpec:
    """One registry entry. ``mapper`` None: frames are counted (``<name>_ignored``), not
    mapped."""

    name: str
    framing: Framing
    mapper: MapperFactory | None


PROTOCOLS: tuple[ProtocolSpec, ...] = (
    ProtocolSpec("ubx", ubx.FRAMING, ubx.UbxMapper),
    ProtocolSpec("rtcm", rtcm.FRAMING, rtcm.RtcmMapper),
    ProtocolSpec("sbf", sbf.FRAMING, sbf.SbfMapper),
    ProtocolSpec("nmea", nmea.FRAMING, None),
)
