"""The :class:`Sink` interface every output implements, its open options, and helpers the
network and serial sinks share."""

from __future__ import annotations

import errno
import ipaddress
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from service.core.errors import BindError, ConfigError

RECORD_CLASSES = ("FIX", "SKY", "TRACK", "STATUS")
"""The record classes a sink may take (see :mod:`service.output.records`)."""

NmeaMode = Literal["", "live", "epoch"]

NMEA_TCP_MAX_CLIENTS = 64
"""NMEA TCP clients served at once by default; more connections are accepted and closed
(setting ``nmea_tcp_max_clients``, see :mod:`service.output.sinks.nmea_tcp`)."""

HTTP_MAX_CLIENTS = 32
"""Connections the status page serves at once by default (a browser tab holds one event
stream); more are accepted and closed (setting ``http_max_clients``, see
:mod:`service.output.sinks.http_page`)."""


@dataclass(frozen=True, slots=True)
class SinkOptions:
    """Settings shared by every output, passed to each factory with its spec string."""

    baud: int = 115200
    append: bool = False  # file outputs: append (the daemon) rather than truncate (replay)
    zmq_curve_secret_key: str = ""
    zmq_curve_clients: str = ""
    nmea_tcp_max_clients: int = NMEA_TCP_MAX_CLIENTS  # nmea-tcp: more clients are refused
    http_max_clients: int = HTTP_MAX_CLIENTS  # http: more connections are refused
    timeline_offset_s: float = 0.0  # http: added to the timeline (replay's built-in scenario)


class Sink:
    """One output. It is handed only what it declares it takes, and may never block.

    ``nmea``: ``"live"`` takes each epoch's lead sentences (RMC, VTG, GGA) as soon as they
    are built, then the epoch's other sentences; ``"epoch"`` takes the epoch's sentences in
    one write, after its JSONL line; ``""`` takes no NMEA. ``records``: the record classes
    (FIX SKY TRACK STATUS) it takes, as dicts, in the order they are published.

    Opening (the constructor or factory) raises :class:`~service.core.errors.BindError` for
    a listener that cannot bind, :class:`~service.core.errors.InputError` for a file or
    device that cannot be opened, :class:`~service.core.errors.ConfigError` for a bad spec.
    Once open, failures are counted and logged, never raised.
    """

    nmea: ClassVar[NmeaMode] = ""
    records: ClassVar[frozenset[str]] = frozenset()

    def write_nmea(self, data: bytes) -> None:
        """NMEA sentences (whole ones, CR LF terminated)."""

    def write_record(self, cls: str, record: Mapping[str, Any]) -> None:
        """One record of class ``cls``."""

    def counters(self) -> Mapping[str, int]:
        """This output's counters, merged into STATUS."""
        return {}

    def reopen(self) -> None:
        """Reopen what logrotate may have renamed (SIGHUP)."""

    def gone(self) -> bool:
        """True once nothing written here can reach anyone (a pipe whose reader left)."""
        return False

    def close(self) -> None:
        """Release the output; nothing is written afterwards."""


SinkFactory = Callable[[str, SinkOptions], Sink]
"""Opens one sink from its spec string (``HOST:PORT``, a path, an endpoint ...)."""


_BIND_ERRNOS = (errno.EADDRINUSE, errno.EADDRNOTAVAIL, errno.EACCES)
"""Bind failures that name the address (BindError); any other is a ConfigError."""


def listening_socket(host: str, port: int, backlog: int, what: str) -> socket.socket:
    """A non-blocking TCP socket listening on ``host:port`` (IPv6 when ``host`` has a colon,
    SO_REUSEADDR) for a server sink named ``what`` in its errors: BindError for an address in
    use, not available or not permitted, ConfigError for any other failure, one line."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    srv = socket.socket(family, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        srv.bind((host, port))
        srv.listen(backlog)
    except OSError as exc:
        srv.close()
        why = "address already in use" if exc.errno == errno.EADDRINUSE else exc.strerror
        error = BindError if exc.errno in _BIND_ERRNOS else ConfigError
        raise error(f"{what} {host}:{port}: {why}") from exc
    srv.setblocking(False)
    return srv


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_host_port(text: str, what: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` too; empty host = 127.0.0.1) or ConfigError."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ConfigError(f"{what} {text!r}: expected HOST:PORT")
    return host.strip("[]") or "127.0.0.1", int(port)
