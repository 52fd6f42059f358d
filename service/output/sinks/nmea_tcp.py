"""``nmea-tcp``: NMEA 0183 to any number of TCP clients (``HOST:PORT``), gpsd style.

A multi-client server in its own thread (selectors). Each client has a bounded output
buffer (and a 64 KiB kernel send buffer); a client that does not read until its buffer
overflows is dropped and counted (``nmea_clients_dropped_slow``), as gpsd does with slow
clients. Whatever clients send (gpsd's ``?WATCH`` etc.) is read and ignored. Listening on
anything but loopback logs a warning.

At most ``max_clients`` (setting ``nmea_tcp_max_clients``, default
:data:`MAX_CLIENTS_DEFAULT`) are served at once: a connection over the cap is accepted and
closed at once (``nmea_clients_refused``), so a flood neither fills the listen backlog
nor takes the process's descriptors. When accept itself fails for want of resources
(EMFILE, ENFILE, ENOBUFS, ENOMEM) the listener is set aside for a growing pause
(:data:`ACCEPT_BACKOFF_MIN_S` to :data:`ACCEPT_BACKOFF_MAX_S`) instead of being polled
again at once, and counted (``nmea_accept_errors``). Both are logged at most once a
minute.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Mapping

from service.core.counters import Counters
from service.core.errors import ConfigError
from service.output.sinks.base import (
    NMEA_TCP_MAX_CLIENTS,
    Sink,
    SinkOptions,
    is_loopback,
    listening_socket,
    parse_host_port,
)

log = logging.getLogger(__name__)

_RESOURCE_ERRNOS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})

MAX_CLIENTS_DEFAULT = NMEA_TCP_MAX_CLIENTS
"""NMEA TCP clients served at once unless configured (``nmea_tcp_max_clients``)."""
LISTEN_BACKLOG = 128
"""Connections the kernel holds until accepted (each is accepted, then served or refused)."""
ACCEPT_BATCH = 64
"""Connections accepted per turn of the I/O loop, so a flood cannot starve the clients."""
ACCEPT_BACKOFF_MIN_S = 0.05
ACCEPT_BACKOFF_MAX_S = 1.0
"""Pause of the listener after accept failed for want of resources, doubling while it does."""
LOG_EVERY_S = 60.0
"""Refusals and accept errors are logged at most this often (all are counted)."""


def open_sink(spec: str, options: SinkOptions) -> NmeaTcpServer:
    return NmeaTcpServer(
        *parse_host_port(spec, "NMEA TCP"), max_clients=options.nmea_tcp_max_clients
    )


class NmeaTcpServer(Sink):
    """NMEA to any number of TCP clients; slow clients are dropped, never waited for.

    ``write_nmea`` only appends to per-client queues under a lock and wakes the I/O thread,
    which accepts, writes whatever each socket takes and closes dropped clients.
    """

    nmea = "live"

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 10110,
        max_buffer_bytes: int = 256 * 1024,
        max_clients: int = MAX_CLIENTS_DEFAULT,
    ) -> None:
        if max_clients < 1:
            raise ConfigError(f"NMEA TCP: at most {max_clients} clients: expected >= 1")
        self.max_buffer_bytes = max_buffer_bytes
        self.max_clients = max_clients
        self.kernel_sndbuf_bytes = 64 * 1024
        self._counters = Counters()
        if not is_loopback(host):
            log.warning("NMEA TCP server listens on %s:%d, not loopback", host, port)
        self._srv = listening_socket(host, port, LISTEN_BACKLOG, "NMEA TCP")
        self.address: tuple[str, int] = self._srv.getsockname()[:2]
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._srv, selectors.EVENT_READ, "listen")
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._lock = threading.Lock()
        self._clients: dict[socket.socket, deque[bytes]] = {}
        self._sizes: dict[socket.socket, int] = {}
        self._doomed: list[socket.socket] = []
        self._accept_paused_until: float | None = None  # monotonic; listener set aside
        self._accept_backoff_s = ACCEPT_BACKOFF_MIN_S
        self._logged_at = {"refused": -math.inf, "accept": -math.inf}
        self._unlogged = {"refused": 0, "accept": 0}
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bdsfix-nmea-tcp", daemon=True)
        self._thread.start()

    def counters(self) -> Mapping[str, int]:
        return self._counters.snapshot() | {"nmea_clients": self.n_clients}

    @property
    def n_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def write_nmea(self, data: bytes) -> None:
        """Send ``data`` to every client; a client whose queue would overflow is dropped.

        A client with nothing queued gets the bytes at once with a non-blocking send from
        the caller's thread (no hand-off to the I/O thread on the latency path); whatever
        the kernel does not take is queued for the I/O thread, behind which later data
        waits, so the order is kept."""
        queued = False
        with self._lock:
            for sock in list(self._clients):
                q = self._clients[sock]
                rest = data
                if not q:
                    try:
                        rest = data[sock.send(data) :]
                    except (BlockingIOError, InterruptedError):
                        pass
                    except OSError:
                        self._doom(sock)
                        continue
                    if not rest:
                        continue
                if self._sizes[sock] + len(rest) > self.max_buffer_bytes:
                    self._doom(sock)
                    self._counters.add("nmea_clients_dropped_slow")
                    log.warning("NMEA client %s too slow: dropped", _peer(sock))
                    continue
                q.append(rest)
                self._sizes[sock] += len(rest)
                queued = True
            queued = queued or bool(self._doomed)
        if queued:
            self._wake()

    def _doom(self, sock: socket.socket) -> None:
        """Forget a client (lock held); the I/O thread closes it."""
        self._clients.pop(sock, None)
        self._sizes.pop(sock, None)
        self._doomed.append(sock)

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # a full wake pipe already means "wake up"
            self._wake_w.send(b"\0")

    def _loop(self) -> None:
        while not self._closed.is_set():
            timeout_s = 0.5
            if self._accept_paused_until is not None:
                timeout_s = max(0.0, min(timeout_s, self._accept_paused_until - time.monotonic()))
            try:
                events = self._sel.select(timeout=timeout_s)
            except (OSError, ValueError):
                return
            if (
                self._accept_paused_until is not None
                and time.monotonic() >= self._accept_paused_until
            ):
                self._accept_paused_until = None
                with contextlib.suppress(KeyError, ValueError):
                    self._sel.register(self._srv, selectors.EVENT_READ, "listen")
            for key, mask in events:
                if key.data == "wake":
                    with contextlib.suppress(OSError):
                        self._wake_r.recv(4096)
                elif key.data == "listen":
                    self._accept()
                elif mask & selectors.EVENT_READ:
                    self._readable(key.fileobj)  # type: ignore[arg-type]
            self._reap()
            self._flush()

    def _accept(self) -> None:
        """Accept what waits (up to :data:`ACCEPT_BATCH`): serve it, or refuse it over the cap."""
        for _ in range(ACCEPT_BATCH):
            try:
                sock, addr = self._srv.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in _RESOURCE_ERRNOS:
                    self._pause_accept(exc)
                    return
                continue  # this connection's own trouble (ECONNABORTED ...): the next one
            self._accept_backoff_s = ACCEPT_BACKOFF_MIN_S
            if self.n_clients >= self.max_clients:
                # counted before the close, so whoever sees the end of stream sees the count
                self._counters.add("nmea_clients_refused")
                sock.close()  # at once: it takes neither a slot nor a descriptor
                self._log_rarely(
                    "refused",
                    "NMEA client %s refused: %d clients connected, the most allowed "
                    "(nmea_tcp_max_clients)",
                    addr,
                    self.max_clients,
                )
                continue
            self._serve(sock, addr)

    def _pause_accept(self, exc: OSError) -> None:
        """Set the listener aside for a while: it stays readable while accept fails, and
        polling it again at once would spin the I/O thread."""
        self._counters.add("nmea_accept_errors")
        self._log_rarely(
            "accept",
            "NMEA TCP accept failed: %s; not accepting for %.2f s",
            exc.strerror,
            self._accept_backoff_s,
        )
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(self._srv)
        self._accept_paused_until = time.monotonic() + self._accept_backoff_s
        self._accept_backoff_s = min(2.0 * self._accept_backoff_s, ACCEPT_BACKOFF_MAX_S)

    def _log_rarely(self, kind: str, msg: str, *args: object) -> None:
        """A warning at most every :data:`LOG_EVERY_S` per kind, with how many went unlogged."""
        now = time.monotonic()
        if now - self._logged_at[kind] < LOG_EVERY_S:
            self._unlogged[kind] += 1
            return
        more = self._unlogged[kind]
        self._logged_at[kind], self._unlogged[kind] = now, 0
        if more:
            msg += f" ({more} more since the last report)"
        log.warning(msg, *args)

    def _serve(self, sock: socket.socket, addr: object) -> None:
        sock.setblocking(False)
        # a bounded kernel send buffer, so a client that never reads is found (and dropped)
        # once our own max_buffer_bytes fills, instead of after megabytes of autotuning
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.kernel_sndbuf_bytes)
        self._counters.add("nmea_clients_accepted")  # counted before it shows in n_clients
        with self._lock:
            self._clients[sock] = deque()
            self._sizes[sock] = 0
        self._sel.register(sock, selectors.EVENT_READ, "client")
        log.info("NMEA client %s connected", addr)

    def _readable(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:  # the client closed (or reset) its end
            with self._lock:
                if sock in self._clients:
                    self._doom(sock)

    def _reap(self) -> None:
        with self._lock:
            doomed, self._doomed = self._doomed, []
        for sock in doomed:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(sock)
            sock.close()

    def _flush(self) -> None:
        with self._lock:
            items = list(self._clients.items())
        for sock, q in items:
            while q:
                chunk = q[0]
                try:
                    n = sock.send(chunk)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    with self._lock:
                        if sock in self._clients:
                            self._doom(sock)
                    break
                with self._lock:
                    if sock not in self._clients:
                        break
                    self._sizes[sock] -= n
                    if n < len(chunk):
                        q[0] = chunk[n:]
                        break
                    q.popleft()
            # ask for write readiness only while bytes wait, so the loop sleeps otherwise
            with self._lock:
                if sock not in self._clients:
                    continue
                want = selectors.EVENT_READ | (selectors.EVENT_WRITE if q else 0)
            with contextlib.suppress(KeyError, ValueError):
                if self._sel.get_key(sock).events != want:
                    self._sel.modify(sock, want, "client")
        self._reap()

    def close(self) -> None:
        """Stop the thread and close every socket."""
        self._closed.set()
        self._wake()
        self._thread.join(timeout=2)
        with self._lock:
            for sock in list(self._clients):
                self._doom(sock)
        self._reap()
        self._sel.close()
        for s in (self._srv, self._wake_r, self._wake_w):
            s.close()


def _peer(sock: socket.socket) -> str:
    try:
        return str(sock.getpeername())
    except OSError:
        return "?"
