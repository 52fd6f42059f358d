"""The input registry: every format bdsfix reads, one entry each.

:data:`PROTOCOLS`: stream protocols, read by the framer and the decoder. An entry names the
protocol (the ``Frame.protocol`` of its frames and the suffix of its counter keys:
``frames_<name>``, ``bad_checksum_<name>``, ...), gives its framing (how a frame is found:
sync pattern, length, check) and the factory of its mapper (frames to events). They mix in
one byte stream (serial, TCP, a capture file).

:data:`FILE_FORMATS`: whole-file formats (RINEX 3 obs, Android GnssLogger logs), read by
:func:`drivers.source.open_source` and :func:`drivers.source.check_capture`. An entry names
the format (its source-spec scheme: ``NAME:PATH`` opens PATH as that format without
detection), says how its content is recognised (``detect(path, head)`` on the file's first
bytes, tried in registry order before the protocols) and gives its reader (path to events).

Adding a protocol or a file format is one module that defines its parts, plus one line
here. The registry is read when a source opens (``drivers.protocols.PROTOCOLS`` /
``FILE_FORMATS`` at that moment), so a test can add an entry with ``monkeypatch.setattr``.

The stream protocols' modules (and pyubx2, pyrtcm, pysbf2, pynmeagps under them) are
imported when :data:`PROTOCOLS` is first read (PEP 562 module ``__getattr__``), not with
this module: ``bdsfix solve`` of a RINEX file never frames a stream, and their imports were
about 30 ms of its start-up.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from drivers import gnsslogger, rinex
from drivers.framing import Event, Framing
from service.core.counters import Counters


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


def _protocols() -> tuple[ProtocolSpec, ...]:
    """The stream protocols: :data:`PROTOCOLS`."""
    from drivers import nmea, rtcm, sbf, ubx

    return (
        ProtocolSpec("ubx", ubx.FRAMING, ubx.UbxMapper),
        ProtocolSpec("rtcm", rtcm.FRAMING, rtcm.RtcmMapper),
        ProtocolSpec("sbf", sbf.FRAMING, sbf.SbfMapper),
        ProtocolSpec("nmea", nmea.FRAMING, None),
    )


def __getattr__(name: str) -> tuple[ProtocolSpec, ...]:
    """``PROTOCOLS``, the stream protocols (UBX, RTCM3, SBF, NMEA), made at its first read
    and kept as a plain module attribute from then on (module docstring)."""
    if name == "PROTOCOLS":
        value = _protocols()
        globals()["PROTOCOLS"] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


FileReader = Callable[[Path, Counters, bool, frozenset[str]], Iterable[Event]]
"""Called as ``reader(path, counters, lenient, systems)``: the file's events in order,
counting what it reads into ``counters``; ``lenient`` (a stream) skips and counts a broken
record where a strict reader (``bdsfix solve``) raises; ``systems`` (RINEX letters, ``--systems``)
are the satellite systems asked for, which a reader may use to leave others out. A
generator's ``finally`` closes the file."""


@dataclass(frozen=True, slots=True)
class FileFormat:
    """One file-format entry: ``name`` (the source-spec scheme ``NAME:PATH`` and the
    ``epochs_<name>`` counter the reader keeps), ``describe`` (its words in "expected ..."
    errors), ``detect(path, head)`` (``head``: the file's first bytes, up to 64 KiB) and
    ``reader``. ``needs_nav(path)``: the file carries no ephemerides bdsfix decodes, so
    ``replay`` and ``run`` refuse it without ``--nav`` (exit 3, naming the day's nav file)
    instead of declining every epoch (None: never refused)."""

    name: str
    describe: str
    detect: Callable[[Path, bytes], bool]
    reader: FileReader
    needs_nav: Callable[[Path], bool] | None = None


FILE_FORMATS: tuple[FileFormat, ...] = (
    FileFormat("rinex", "a RINEX 3 obs file", rinex.detect, rinex.obs_events),
    FileFormat(
        "gnsslogger",
        "an Android GnssLogger log",
        gnsslogger.detect,
        gnsslogger.events,
        gnsslogger.needs_nav,
    ),
)
