"""Byte transports (file, serial, TCP client) behind one small interface, and replay pacing.

A transport's ``read(max_bytes)`` returns the bytes available now, possibly ``b""`` after a
short timeout; ``finished`` turns true only at the end of a file. ``close()`` releases the
descriptor. Serial and TCP transports survive a vanished device or a closed connection: they
log the disconnect, count it, close the descriptor and retry with exponential backoff
(``backoff_initial_s`` doubling up to ``backoff_max_s``, :data:`RECONNECT_MAX_S` = 0.5 s by
default), so reading resumes within that time (plus one read timeout) of the device or server
coming back: well inside the 2 s the daemon promises. Only the first failed attempt of an
outage is logged as a warning, the rest at debug level; the reconnection is logged with the
outage's length. A transport never holds more than its one descriptor, whatever the number of
disconnections. Transports know nothing about protocols.

Counter keys: ``transport_bytes``, ``disconnects``, ``reconnects``, ``connects``,
``open_failures``, ``drops_before_data`` (see :class:`_Reconnecting`).
"""

from __future__ import annotations

import ipaddress
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Protocol, TypeVar

from service.core.counters import Counters
from service.core.errors import ConfigError, InputError
from service.core.ratelog import RateLimitedLog
from service.core.timebase import diff_s
from service.core.types import MeasurementEpoch

# pyserial and socket are imported by the transports that use them, when they connect: a file
# source (bdsfix solve, the replay of a capture) needs neither (~4 ms of its start-up)
if TYPE_CHECKING:
    import socket

    import serial

log = logging.getLogger(__name__)

T = TypeVar("T")

RECONNECT_MAX_S = 0.5
"""Longest wait between two attempts to reopen a lost device or connection [s]."""
READ_TIMEOUT_S = 0.1
"""Longest a serial or TCP ``read`` waits, for bytes or (while the line is down) between
two attempts to reopen it [s]: the daemon's loop, which reads in its own thread, keeps its
timers and notices a stop request at least this often (a TCP connect attempt may take up
to its ``connect_timeout_s``)."""


class Transport(Protocol):
    """What every transport offers."""

    name: str
    counters: Counters

    @property
    def finished(self) -> bool: ...

    def read(self, max_bytes: int = 4096) -> bytes: ...

    def close(self) -> None: ...


class FileTransport:
    """Chunks of a file (path or open binary file object such as ``sys.stdin.buffer``)."""

    def __init__(
        self, path: str | Path | IO[bytes], *, name: str | None = None, chunk_size: int = 65536
    ) -> None:
        if isinstance(path, str | Path):
            self._file: IO[bytes] = open(path, "rb")  # noqa: SIM115 - closed in close()
            self._owned = True
            self.name = name or str(path)
        else:
            self._file = path
            self._owned = False
            self.name = name or str(getattr(path, "name", "file"))
        self.chunk_size = chunk_size
        self.counters = Counters()
        self._finished = False
        self._read: Callable[[int], bytes] = getattr(self._file, "read1", self._file.read)

    @property
    def finished(self) -> bool:
        return self._finished

    def read(self, max_bytes: int = 4096) -> bytes:
        if self._finished:
            return b""
        data = self._read(max(1, min(max_bytes, self.chunk_size)))
        if not data:
            self._finished = True
        self.counters["transport_bytes"] += len(data)
        return data

    def close(self) -> None:
        self._finished = True
        if self._owned:
            self._file.close()


class _Reconnecting:
    """Connect on demand; on failure, back off exponentially up to ``backoff_max_s``.

    A connection is *confirmed* when it has proved to work: at once for a device or a TCP
    server (the default), or, for a transport with ``confirm_by_data`` (NTRIP), when the
    subclass has seen real data on it (:meth:`_confirmed`). Only a confirmed connection
    resets the backoff, ends an outage ("reconnected after") and makes its loss a new outage
    (one WARNING "disconnected"). A connection lost before it was confirmed (a server that
    accepts and closes at once, or answers and sends nothing usable) is counted
    ``drops_before_data`` and the backoff goes on doubling; its log line is rate-limited
    (:class:`~service.core.ratelog.RateLimitedLog`: the first at once, then at most one a
    minute saying how many it stands for), so such a server gets a connection every
    ``backoff_max_s`` and the journal a line a minute, not a storm of both."""

    confirm_by_data = False

    def __init__(
        self,
        name: str,
        *,
        timeout_s: float,
        backoff_initial_s: float,
        backoff_max_s: float,
    ) -> None:
        self.name = name
        self.counters = Counters()
        self.timeout_s = timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self._backoff_s = backoff_initial_s
        self._next_try = 0.0
        self._ever_connected = False  # ever confirmed
        self._healthy = False  # the current connection is confirmed
        self._failures_logged = 0
        self._closed = False
        self._down_since: float | None = None
        self._drop_log = RateLimitedLog(log)

    @property
    def finished(self) -> bool:
        return self._closed

    @property
    def waits_bounded(self) -> bool:
        """Whether every ``read`` returns within about ``timeout_s`` (plus, for TCP, a
        connect attempt's ``connect_timeout_s``), so a loop may read in its own thread."""
        return True

    @property
    def connected(self) -> bool:
        return self._handle() is not None

    # subclass hooks
    def _handle(self) -> Any:
        raise NotImplementedError

    def _connect(self) -> None:
        raise NotImplementedError

    def _read_now(self, max_bytes: int) -> bytes:
        raise NotImplementedError

    def _release(self) -> None:
        raise NotImplementedError

    def open_now(self) -> None:
        """Open at once, as a start-up check: a failure raises InputError naming the device."""
        if self._handle() is not None:
            return
        try:
            self._connect()
        except (OSError, ValueError) as err:  # pyserial's SerialException is an OSError
            self.counters["open_failures"] += 1
            raise InputError(f"{self.name}: cannot open: {_why(err)}") from err
        self.counters["connects"] += 1
        if not self.confirm_by_data:
            self._ever_connected = self._healthy = True
        log.debug("%s: connected", self.name)  # the caller reports its start-up in one line

    def _ensure(self) -> bool:
        if self._handle() is not None:
            return True
        now = time.monotonic()
        if now < self._next_try:
            time.sleep(min(self._next_try - now, self.timeout_s))
            return False
        try:
            self._connect()
        except (OSError, ValueError) as err:  # pyserial's SerialException is an OSError
            self.counters["open_failures"] += 1
            level = logging.WARNING if self._failures_logged == 0 else logging.DEBUG
            self._failures_logged += 1
            log.log(
                level,
                "%s: cannot open (%s); retry in %.1f s",
                self.name,
                _why(err),
                self._backoff_s,
            )
            self._next_try = time.monotonic() + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)
            return False
        if self._closed:  # close() ran while we were connecting (reader thread)
            self._release()
            return False
        self.counters["connects"] += 1
        if self.confirm_by_data:
            log.debug("%s: connected; waiting for data", self.name)
        else:
            self._confirmed()
        return True

    def _confirmed(self) -> None:
        """The current connection works: end the outage, reset the backoff (once)."""
        if self._healthy:
            return
        self._healthy = True
        if self._ever_connected:
            self.counters["reconnects"] += 1
            down_s = time.monotonic() - (self._down_since or time.monotonic())
            log.warning("%s: reconnected after %.1f s", self.name, down_s)
        else:
            log.info("%s: connected", self.name)
        self._ever_connected = True
        self._down_since = None
        self._failures_logged = 0
        self._backoff_s = self.backoff_initial_s

    def _drop(self, reason: object) -> None:
        self.counters["disconnects"] += 1
        was_healthy = self._healthy
        self._release()  # sees the connection as it was (confirmed or not)
        self._healthy = False
        if was_healthy:
            log.warning("%s: disconnected (%s); reconnecting", self.name, _why(reason))
            self._down_since = time.monotonic()
        else:
            self.counters["drops_before_data"] += 1
            self._drop_log.warning(
                "drop",
                "%s: connection lost before any data (%s); retry in %.1f s",
                self.name,
                _why(reason),
                self._backoff_s,
            )
        self._next_try = time.monotonic() + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)

    def read(self, max_bytes: int = 4096) -> bytes:
        """Bytes available within about ``timeout_s``; ``b""`` while disconnected."""
        if self._closed or not self._ensure():
            return b""
        try:
            data = self._read_now(max_bytes)
        except OSError as err:  # pyserial's SerialException is one
            self._drop(err)
            return b""
        self.counters["transport_bytes"] += len(data)
        return data

    def close(self) -> None:
        self._closed = True
        self._release()


def _why(err: object) -> str:
    """An OS error as its strerror (pyserial wraps errno errors in long messages)."""
    code = getattr(err, "errno", None)
    if isinstance(code, int) and code > 0:
        return os.strerror(code)
    return str(err)


class SerialTransport(_Reconnecting):
    """A serial device via pyserial, reopened after it vanishes or errors."""

    def __init__(
        self,
        device: str,
        baud: int = 38400,
        *,
        timeout_s: float = READ_TIMEOUT_S,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = RECONNECT_MAX_S,
    ) -> None:
        super().__init__(
            f"serial:{device}:{baud}",
            timeout_s=timeout_s,
            backoff_initial_s=backoff_initial_s,
            backoff_max_s=backoff_max_s,
        )
        self.device = device
        self.baud = baud
        self._ser: serial.Serial | None = None
        self._polled: tuple[Any, Any] | None = None  # (the port, a poll of its descriptor)

    def _handle(self) -> Any:
        return self._ser

    def _connect(self) -> None:
        import serial

        self._ser = serial.Serial(self.device, self.baud, timeout=self.timeout_s)

    def _read_now(self, max_bytes: int) -> bytes:
        if isinstance(getattr(self._ser, "fd", None), int):
            return self._read_polled(max_bytes)
        if self._ser is None:
            from serial import SerialException

            raise SerialException("not open")
        data = bytes(self._ser.read(1))  # waits up to timeout_s
        if data and max_bytes > 1:
            waiting = self._ser.in_waiting
            if waiting:
                data += bytes(self._ser.read(min(waiting, max_bytes - 1)))
        return data

    def _release(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except OSError as err:  # pragma: no cover - best effort (SerialException too)
                log.debug("%s: close failed: %s", self.name, err)

    def _read_polled(self, max_bytes: int) -> bytes:
        """One wait and one read of what has arrived, on the descriptor of pyserial's POSIX
        port (opened non-blocking): pyserial's read(1), in_waiting and read(n) cost two
        waits, two reads and an ioctl between an epoch's last byte and its decoding. As
        from pyserial, a read error is an OSError and a device that is ready but gives
        nothing has gone."""
        ser = self._ser
        held = self._polled
        if held is None or held[0] is not ser:
            import select

            poll = select.poll()
            poll.register(ser.fd, select.POLLIN)  # type: ignore[union-attr]
            held = self._polled = (ser, poll)
        if not held[1].poll(self.timeout_s * 1e3):
            return b""
        try:
            data = os.read(ser.fd, max_bytes)  # type: ignore[union-attr]
        except BlockingIOError:
            return b""
        if not data:
            raise OSError("device ready to read but returned no data (disconnected?)")
        return data


class TcpClientTransport(_Reconnecting):
    """A TCP client (e.g. a receiver's TCP port or ``str2str``), reconnecting on loss."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        timeout_s: float = READ_TIMEOUT_S,
        connect_timeout_s: float = 2.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = RECONNECT_MAX_S,
    ) -> None:
        super().__init__(
            f"tcp:{host}:{port}",
            timeout_s=timeout_s,
            backoff_initial_s=backoff_initial_s,
            backoff_max_s=backoff_max_s,
        )
        self.host = host
        self.port = port
        self.connect_timeout_s = connect_timeout_s
        self._sock: socket.socket | None = None

    def _handle(self) -> Any:
        return self._sock

    @property
    def waits_bounded(self) -> bool:
        """Only for an address (or ``localhost``): a host name is resolved at each connect
        attempt, and a resolver that does not answer can hold it for tens of seconds."""
        if self.host == "localhost":
            return True
        try:
            ipaddress.ip_address(self.host.strip("[]"))
        except ValueError:
            return False
        return True

    def _connect(self) -> None:
        import socket

        sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        sock.settimeout(self.timeout_s)
        self._sock = sock

    def _read_now(self, max_bytes: int) -> bytes:
        if self._sock is None:
            raise ConnectionResetError("not connected")
        try:
            data = self._sock.recv(max_bytes)
        except TimeoutError:
            return b""
        if not data:
            raise ConnectionResetError("connection closed by peer")
        return data

    def _release(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()


def pace(
    events: Iterable[T],
    speed: float | None,
    *,
    max_gap_s: float = 60.0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[T]:
    """Yield ``events`` so that measurement-epoch times advance at ``speed`` x real time.

    ``speed=None`` yields as fast as possible. Only :class:`MeasurementEpoch` times pace the
    stream; other events pass at once. A time step backwards or a gap longer than
    ``max_gap_s`` (data time) re-anchors instead of sleeping.
    """
    if speed is None:
        yield from events
        return
    if not (speed > 0 and math.isfinite(speed)):
        raise ConfigError(f"replay speed must be a positive number, got {speed}")
    anchor: tuple[int, float, float] | None = None  # data week, tow, wall clock
    last: tuple[int, float] | None = None
    for ev in events:
        if isinstance(ev, MeasurementEpoch):
            t = (ev.gpst_week, ev.gpst_tow_s)
            step = None if last is None else diff_s(*t, *last)
            if anchor is None or step is None or step < 0 or step > max_gap_s:
                anchor = (t[0], t[1], clock())
            else:
                target = anchor[2] + diff_s(*t, anchor[0], anchor[1]) / speed
                delay = target - clock()
                if delay > 0:
                    sleep(delay)
            last = t
        yield ev
