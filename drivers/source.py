"""One entry point from a source spec to a stream of events, with protocol auto-detection.

``open_source(spec)`` accepts a file path (a file of a registered file format or a binary
capture), ``NAME:PATH`` (PATH read as the registered file format NAME, e.g.
``gnsslogger:log.txt``, ``rinex:obs.24o``), ``file:PATH``, ``-`` (standard input),
``serial:/dev/ttyX[:baud]`` or a bare ``/dev/...`` path, and ``tcp:host:port``. The file
formats of :data:`drivers.protocols.FILE_FORMATS` (RINEX 3 obs, Android GnssLogger logs)
are recognised by their content and read by their own reader (:class:`FileSource`);
everything else goes through :class:`StreamDecoder`: the framer and the mappers of the
protocols registered in :data:`drivers.protocols.PROTOCOLS` (UBX, RTCM3, SBF and NMEA, mixed in
one stream) behind a ``feed(bytes) -> events`` interface, for an asyncio daemon or any other
byte pump.

Counter keys added here, ``<p>`` being a protocol name: ``decode_errors_<p>`` (library parse
failures of checksum-valid frames), ``map_errors_<p>`` (unexpected content), ``<p>_ignored``
for a protocol without a mapper (``nmea_ignored``), ``events``, ``nav_ephemerides``,
``idle_flushes``.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import stat
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers import protocols as _registry
from drivers.framing import Event, Frame, Framer, WeekContext
from drivers.protocols import FileFormat, Mapper, ProtocolSpec
from drivers.transport import (
    FileTransport,
    SerialTransport,
    TcpClientTransport,
    Transport,
    _Reconnecting,
    pace,
)
from service.core.counters import Counters
from service.core.errors import ConfigError, DecodeError, InputError
from service.core.ratelog import RateLimitedLog
from service.core.systems import DEFAULT_SYSTEMS
from service.core.timebase import MIN_SANE_GPS_WEEK, gpst_from_utc

if TYPE_CHECKING:
    from drivers.rinex import NavData

log = logging.getLogger(__name__)

__all__ = [
    "BinarySource",
    "EventSource",
    "FileSource",
    "StreamDecoder",
    "file_spec",
    "is_rinex",
    "open_source",
    "pace",
]

DEFAULT_BAUD = 38400
READ_SIZE = 4096


class StreamDecoder:
    """Framer + the mappers of ``protocols``: ``feed(data)`` returns the events the bytes
    complete.

    ``gps_week`` seeds the week for messages that carry only a time of week (RTCM MSM, UBX
    MEASX) until the stream itself gives one. By protocol name, ``max_payload`` overrides a
    payload bound and ``mapper_options`` gives a mapper's keyword options (e.g. ``{"ubx":
    {"measx_offset_m": ...}}`` presets the RAWX-MEASX calibration of :mod:`drivers.ubx`).
    Library exceptions are caught here and counted; they never stop the stream.
    """

    def __init__(
        self,
        *,
        gps_week: int | None = None,
        max_payload: Mapping[str, int] | None = None,
        mapper_options: Mapping[str, Mapping[str, Any]] | None = None,
        counters: Counters | None = None,
        protocols: Sequence[ProtocolSpec] | None = None,
    ) -> None:
        if protocols is None:  # the registry as it is now (a test may have added to it)
            protocols = _registry.PROTOCOLS
        self.counters = counters if counters is not None else Counters()
        self.week = WeekContext(gps_week)
        self.framer = Framer(protocols, self.counters, max_payload=max_payload)
        self._log = RateLimitedLog(log)
        options = dict(mapper_options or {})
        unknown = options.keys() - {p.name for p in protocols if p.mapper is not None}
        if unknown:
            raise ValueError(f"mapper_options: no mapper for {sorted(unknown)}")
        self.mappers: dict[str, Mapper] = {
            p.name: p.mapper(self.counters, self.week, **options.get(p.name, {}))
            for p in protocols
            if p.mapper is not None
        }

    def feed(self, data: bytes) -> list[Event]:
        """Decode a chunk of bytes; returns complete events in stream order."""
        return self._decode(self.framer.feed(data))

    def flush(self) -> list[Event]:
        """End of stream: held bytes, then pending epochs."""
        events = self._decode(self.framer.flush())
        return events + self.flush_pending()

    def flush_pending(self) -> list[Event]:
        """Emit epochs still waiting for messages (idle line); framing state is kept."""
        events: list[Event] = [e for m in self.mappers.values() for e in m.flush()]
        self.counters["events"] += len(events)
        return events

    def decode_frame(self, frame: Frame) -> list[Event]:
        """Events from one frame; a library or mapping failure is counted, not raised."""
        mapper = self.mappers.get(frame.protocol)
        if mapper is None:
            self.counters[f"{frame.protocol}_ignored"] += 1
            return []
        try:
            return mapper.on_frame(frame.raw)
        except DecodeError as err:
            self.counters[f"map_errors_{frame.protocol}"] += 1
            self._log.warning(
                frame.protocol, "%s frame at offset %d: %s", frame.protocol, frame.offset, err
            )
        except Exception as err:  # library parse errors of any kind stop here
            # A frame whose checksum held but which its library or mapper cannot read is
            # rare on a real stream (a newer message version, or a bug): said, rate-limited,
            # with the traceback at DEBUG, never only counted
            self.counters[f"decode_errors_{frame.protocol}"] += 1
            self._log.warning(
                f"{frame.protocol}:decode",
                "%s frame at offset %d not decoded (%s: %s); counted decode_errors_%s",
                frame.protocol,
                frame.offset,
                type(err).__name__,
                err,
                frame.protocol,
            )
            log.debug("%s frame at offset %d", frame.protocol, frame.offset, exc_info=True)
        return []

    def _decode(self, frames: list[Frame]) -> list[Event]:
        events: list[Event] = []
        for frame in frames:
            events += self.decode_frame(frame)
        self.counters["events"] += len(events)
        return events


class EventSource:
    """Iterable of events with ``counters``; a context manager that closes its input."""

    counters: Counters
    name: str

    def __iter__(self) -> Iterator[Event]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        """Release the input."""

    def __enter__(self) -> EventSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class BinarySource(EventSource):
    """Any transport through a :class:`StreamDecoder`.

    After ``idle_flush_s`` without bytes, epochs still waiting for a message are emitted,
    so a receiver that stops mid-epoch does not hold its last epoch back.
    """

    def __init__(
        self,
        transport: Transport,
        decoder: StreamDecoder | None = None,
        *,
        prefix: Iterable[Event] = (),
        idle_flush_s: float = 0.5,
        read_size: int = READ_SIZE,
    ) -> None:
        self.transport = transport
        self.decoder = decoder if decoder is not None else StreamDecoder()
        self.counters = self.decoder.counters
        self.counters.update(transport.counters)
        transport.counters = self.counters  # one set of counters for the whole stream
        self.name = transport.name
        self._prefix = list(prefix)
        self.idle_flush_s = idle_flush_s
        self.read_size = read_size
        self.read_at_s = 0.0
        """:func:`time.perf_counter` when the last read that gave bytes returned (the
        latency figures of ``bench/bench_latency.py``)."""

    @property
    def live(self) -> bool:
        """True for a serial source and a TCP source given by address: a read returns
        within the transport's timeout (:data:`drivers.transport.READ_TIMEOUT_S`) even while
        nothing comes or the line is down, so :meth:`ticks` can be read in a loop that keeps
        timers of its own (a TCP host name is resolved at each connect attempt, which a
        silent resolver can hold for tens of seconds: not live)."""
        return isinstance(self.transport, _Reconnecting) and self.transport.waits_bounded

    def __iter__(self) -> Iterator[Event]:
        return (ev for ev in self.ticks() if ev is not None)

    def ticks(self) -> Iterator[Event | None]:
        """The events, and ``None`` after each read once its events are out: the bytes read
        so far are all handled (for a live source also after a read that timed out or found
        the line down), a gap where the caller's periodic work delays no event."""
        yield from self._prefix
        idle_since: float | None = None
        while True:
            data = self.transport.read(self.read_size)
            if data:
                self.read_at_s = time.perf_counter()
                idle_since = None
                yield from self.decoder.feed(data)
                yield None
                continue
            if self.transport.finished:
                yield from self.decoder.flush()
                return
            now = time.monotonic()
            if idle_since is None:
                idle_since = now
            elif now - idle_since >= self.idle_flush_s:
                pending = self.decoder.flush_pending()
                if pending:
                    self.counters["idle_flushes"] += 1
                    yield from pending
                idle_since = now
            yield None

    def close(self) -> None:
        self.transport.close()


class FileSource(EventSource):
    """A file of a registered file format (:data:`drivers.protocols.FILE_FORMATS`) through
    its reader.

    A stream is ``lenient`` by default: a broken record is logged with file:line, counted and
    skipped, as the framer does with bad bytes; ``bdsfix solve`` keeps the strict reader and
    its error. Counts ``events``; the reader counts the rest into the same counters.
    """

    def __init__(
        self,
        path: str | Path,
        fmt: FileFormat,
        *,
        prefix: Iterable[Event] = (),
        lenient: bool = True,
        systems: Iterable[str] = DEFAULT_SYSTEMS,
    ) -> None:
        self.name = str(path)
        self.format = fmt
        self.counters = Counters()
        self._events: Iterable[Event] = fmt.reader(
            Path(path), self.counters, lenient, frozenset(systems)
        )
        self._prefix = list(prefix)

    def __iter__(self) -> Iterator[Event]:
        yield from self._prefix
        for ev in self._events:
            self.counters["events"] += 1
            yield ev

    def close(self) -> None:
        closer: Callable[[], None] | None = getattr(self._events, "close", None)
        if closer is not None:
            closer()


DETECT_BYTES = 1 << 16
"""How much of a file the file formats' detection sees."""
CAPTURE_SCAN_BYTES = 1 << 20
"""How much of a capture file :func:`check_capture` reads for a first frame."""


def file_format(path: str | Path) -> FileFormat | None:
    """The registered file format (:data:`drivers.protocols.FILE_FORMATS`) whose detection
    accepts the file's first bytes, in registry order; None: a byte stream for the framer."""
    from drivers import protocols

    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(DETECT_BYTES)
    return next((f for f in protocols.FILE_FORMATS if f.detect(path, head)), None)


def expected_inputs() -> str:
    """The "expected ..." words of an input refusal, from the registry."""
    from drivers import protocols

    frames = ", ".join(p.name.upper() for p in protocols.PROTOCOLS)
    files = [f.describe for f in protocols.FILE_FORMATS]
    return f"expected a capture of {frames} frames, {', '.join(files[:-1])} or {files[-1]}"


def check_capture(path: str | Path, scan_bytes: int = CAPTURE_SCAN_BYTES) -> None:
    """A capture file must hold something bdsfix reads: a registered file format, or at
    least one frame of a registered protocol in its first ``scan_bytes``. Otherwise
    InputError (exit 3) with one line saying what was expected."""
    from drivers import protocols
    from drivers.rinex import COMPRESSED_MAGICS

    path = Path(path)
    if file_format(path) is not None:
        return
    with open(path, "rb") as fh:
        head = fh.read(scan_bytes)
    expected = expected_inputs()
    if not head:
        raise InputError(f"{path}: empty file; {expected}")
    if head.startswith((*COMPRESSED_MAGICS, b"BZh", b"PK\x03\x04", b"\xfd7zXZ")):
        raise InputError(f"{path}: a compressed archive, not a capture: decompress it first")
    framer = Framer(protocols.PROTOCOLS)
    if not framer.feed(head) and not framer.flush():
        raise InputError(f"{path}: no frame found in its first {len(head)} bytes; {expected}")


def file_epochs(
    path: str | Path, *, lenient: bool = False, systems: Iterable[str] = DEFAULT_SYSTEMS
) -> tuple[Iterator[Event], Counters]:
    """The events of a file of a registered file format (``bdsfix solve`` and ``ttff``: RINEX
    3 obs, GnssLogger logs, ...) and the counters its reader keeps; ``NAME:PATH`` names the
    format; ``systems``: the satellite systems (RINEX letters) to read where the format
    chooses. InputError (exit 3) for a file of none of them."""
    fmt, name = file_spec(str(path))
    if not os.path.isfile(name):
        raise InputError(f"{name}: no such file")
    fmt = fmt or file_format(name)
    if fmt is None:
        formats = ", ".join(f.describe for f in _registry.FILE_FORMATS)
        raise InputError(f"{name}: not a file bdsfix solves; expected {formats}")
    counters = Counters()
    return iter(fmt.reader(Path(name), counters, lenient, frozenset(systems))), counters


def is_rinex(path: str | Path) -> bool:
    """True when the file is RINEX (its first line carries the RINEX header label; also
    gzip, Unix compress and Hatanaka compact RINEX): :func:`drivers.rinex.detect`."""
    from drivers.rinex import detect

    with open(path, "rb") as f:
        head = f.readline(200)
    return detect(Path(path), head)


def _nav_events(
    nav: str | Path | NavData | Iterable[str | Path | NavData] | None,
    counters: Counters,
    systems: Iterable[str] = DEFAULT_SYSTEMS,
) -> list[Event]:
    if nav is None:
        return []
    from drivers.rinex import read_nav

    items = [nav] if isinstance(nav, str | Path) or not isinstance(nav, Iterable) else list(nav)
    events: list[Event] = []
    for item in items:
        data = read_nav(item, systems) if isinstance(item, str | Path) else item
        for ephs in data.ephemerides.values():
            events.extend(ephs)
            counters["nav_ephemerides"] += len(ephs)
        for name in ("iono_bds", "iono_gps", "ggto"):
            params = getattr(data, name, None)
            if params is not None:
                events.append(params)
    return events


def _is_char_device(path: str) -> bool:
    """A serial device or pty given by any path (e.g. a udev or test symlink)."""
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return False


def serial_device(spec: str, baud: int) -> tuple[str, int]:
    """(device, baud) of a serial source spec, ``serial:DEV[:BAUD]`` or a device path
    (``baud`` unless the spec names one)."""
    rest = spec.removeprefix("serial:")
    device, sep, rate = rest.rpartition(":")
    if not sep or not rate.isdigit():
        return rest, baud
    return device, int(rate)


def file_spec(spec: str) -> tuple[FileFormat | None, str]:
    """(format named by the spec's scheme or None, path) of a file source spec:
    ``NAME:PATH`` for a registered file format, ``file:PATH`` or ``PATH`` (detected)."""
    from drivers import protocols

    scheme, sep, rest = spec.partition(":")
    if sep:
        for fmt in protocols.FILE_FORMATS:
            if fmt.name == scheme:
                return fmt, rest
    return None, spec.removeprefix("file:")


def open_source(
    spec: str,
    *,
    nav: str | Path | NavData | Iterable[str | Path | NavData] | None = None,
    gps_week: int | None = None,
    baud: int = DEFAULT_BAUD,
    max_payload: Mapping[str, int] | None = None,
    mapper_options: Mapping[str, Mapping[str, Any]] | None = None,
    idle_flush_s: float = 0.5,
    reconnect_max_s: float = 2.0,
    systems: Iterable[str] = DEFAULT_SYSTEMS,
) -> EventSource:
    """Open ``spec`` and return an iterable of events with ``.counters``.

    ``nav`` (RINEX nav file or files, as paths or as already read) puts its ephemerides and
    ionosphere parameters at the head of the stream, as held ephemerides. Pace a replay
    with :func:`pace`.
    ``max_payload`` and ``mapper_options`` go to :class:`StreamDecoder`. ``systems`` (RINEX
    letters) are the systems read from RINEX observation and nav files, RTCM MSM and
    ephemerides, UBX RXM-RAWX, RXM-MEASX and the GPS/Galileo subframes of UBX RXM-SFRBX, SBF
    MeasEpoch and the GPS and Galileo navigation blocks (BeiDou alone by default).

    The GPS week for RTCM MSM times of week comes from the stream (UBX RAWX / NAV-TIMEGPS /
    NAV-PVT, the ephemerides RTCM 1019/1042/1044/1045/1046), with ``gps_week`` or, for live
    sources (serial, TCP), the system clock as a hint until then (:class:`WeekContext`).
    Epochs seen before any week is known are passed on with
    :data:`~service.core.types.UNKNOWN_WEEK` (counted, ``msm_no_week``) and declined by the
    pipeline (``no_time``).
    """
    counters = Counters()
    prefix = _nav_events(nav, counters, systems)
    transport: Transport
    if spec.startswith("tcp:"):
        host, _, port = spec[4:].rpartition(":")
        if not host or not port.isdigit():
            raise ConfigError(f"bad TCP source {spec!r}: expected tcp:HOST:PORT")
        transport = TcpClientTransport(host, int(port), backoff_max_s=reconnect_max_s)
    elif spec.startswith(("serial:", "/dev/")) or _is_char_device(spec):
        device, rate = serial_device(spec, baud)
        transport = SerialTransport(device, rate, backoff_max_s=reconnect_max_s)
    elif spec == "-":
        transport = FileTransport(sys.stdin.buffer, name="stdin")
    else:
        fmt, path = file_spec(spec)
        if not os.path.isfile(path):
            raise ConfigError(f"source {spec!r}: no such file")
        fmt = fmt or file_format(path)
        if fmt is not None:
            src = FileSource(path, fmt, prefix=prefix, systems=systems)
            src.counters.update(counters)
            return src
        transport = FileTransport(path)
    options = {k: dict(v) for k, v in (mapper_options or {}).items()}
    if frozenset(systems) != frozenset(DEFAULT_SYSTEMS):  # RTCM MSM and ephemerides of these
        options.setdefault("rtcm", {})["systems"] = frozenset(systems)
        options.setdefault("ubx", {})["systems"] = frozenset(systems)
        options.setdefault("sbf", {})["systems"] = frozenset(systems)
    decoder = StreamDecoder(
        gps_week=gps_week,
        max_payload=max_payload,
        mapper_options=options,
        counters=counters,
    )
    if gps_week is None and not isinstance(transport, FileTransport):
        # A live stream happens now: the system clock hints the week until the data gives
        # it, unless the clock is unset. A file may be years old: its week comes from itself.
        now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
        week, tow = gpst_from_utc(now)
        if week >= MIN_SANE_GPS_WEEK:
            decoder.week.set_hint(week, tow)
        else:
            log.warning("system clock reads %s UTC, not set: the GPS week waits for the data", now)
    return BinarySource(transport, decoder, prefix=prefix, idle_flush_s=idle_flush_s)
