"""``http``: a live status page for a browser, ``HOST:PORT`` (``--output http:127.0.0.1:8080``).

Read-only, and only these routes (a fixed table: nothing is ever looked up on disk):

- ``/``: one self-contained page, the package's own asset ``status_page.html`` read once
  at open through :mod:`importlib.resources` (its script and style inline; no external
  script, font, image, map tile or CDN, so it works offline): a sky plot, C/N0 bars, the
  current fix, an east/north scatter of the last minutes of fixes, the time-to-first-fix
  timeline and the STATUS counters;
- ``/events``: Server-Sent Events (``text/event-stream``): ``state`` at connect (the latest
  records, the timeline, the recent fixes and the fix-mode changes), then ``fix``, ``sky``,
  ``status`` and ``timeline`` as records come;
- ``/fix.json``, ``/status.json``: the latest FIX and STATUS records as published (503
  until the first).

Anything else gets 404, including a request head over :data:`MAX_HEAD_BYTES`; a method
other than GET or HEAD gets 405. Every answer carries a Content-Security-Policy (the
page's script and style by their SHA-256, ``connect-src 'self'``, nothing else; no
framing), ``X-Content-Type-Options: nosniff``, ``Referrer-Policy: no-referrer``,
``X-Frame-Options: DENY``, ``Cache-Control: no-store`` and ``Cross-Origin-Resource-Policy:
same-origin``. Listening on loopback (the default), a request whose ``Host`` names
anything but a loopback address or ``localhost`` gets 421, so a web page that rebinds its
own host name to 127.0.0.1 cannot read the receiver's position. Listening on anything
but loopback logs the warning the ZeroMQ and NMEA TCP outputs give.

Never slows the epoch loop: :meth:`HttpPageServer.write_record` (the loop's thread) only
appends the record to a bounded in-box and wakes the sink's own I/O thread, which encodes
each record once, keeps the page's state and writes to the clients with non-blocking
sends. Each client has a bounded backlog (:data:`CLIENT_BACKLOG_BYTES`, and a 64 KiB
kernel send buffer); a client whose backlog overflows (a stalled or slow browser) is
dropped and counted (``http_clients_dropped_slow``). At most ``max_clients`` connections
(setting ``http_max_clients``) are open at once; one more is accepted and closed
(``http_clients_refused``), as NMEA TCP does. A connection that has not sent its request
head within :data:`HEAD_TIMEOUT_S` is closed.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import ipaddress
import logging
import math
import re
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from service.core.bds import orbit_class
from service.core.counters import Counters
from service.core.errors import ConfigError, InputError
from service.output.records import dumps
from service.output.sinks.base import (
    HTTP_MAX_CLIENTS,
    RECORD_CLASSES,
    Sink,
    SinkOptions,
    is_loopback,
    listening_socket,
    parse_host_port,
)
from service.output.timeline import ORDER, Timeline

log = logging.getLogger(__name__)

PAGE_ASSET = "status_page.html"
"""The page, a file of this package (read once at open, never per request)."""
MAX_HEAD_BYTES = 8192
"""A request head (request line and headers) longer than this is not ours: 404."""
HEAD_TIMEOUT_S = 10.0
"""A connection whose request head is not whole after this long is closed."""
CLIENT_BACKLOG_BYTES = 512 * 1024
"""Bytes queued for one client beyond what its socket took; more drops the client."""
KERNEL_SNDBUF_BYTES = 64 * 1024
INBOX_RECORDS = 4096
"""Records waiting for the I/O thread; beyond that the oldest go (``http_records_dropped``)."""
HISTORY_S = 300.0
"""Data time of the fixes the scatter shows [s]."""
HISTORY_STEP_S = 0.5
"""The scatter keeps one fix per this much data time [s]."""
MODE_CHANGES = 200
"""Fix-mode changes kept for the page's mode strip."""
KEEPALIVE_S = 15.0
"""An SSE comment this often, so a vanished browser's connection is found."""
LISTEN_BACKLOG = 64
LOG_EVERY_S = 60.0

_REQUEST_LINE = re.compile(rb"^([A-Z]{1,16}) (\S{1,8192}) HTTP/1\.[01]$")
_ROUTES = frozenset({"/", "/events", "/fix.json", "/status.json"})
_TEXT = "text/plain; charset=utf-8"
_REASONS = {
    200: "OK",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    421: "Misdirected Request",
    503: "Service Unavailable",
}


def open_sink(spec: str, options: SinkOptions) -> HttpPageServer:
    host, port = parse_host_port(spec, "HTTP status page")
    return HttpPageServer(
        host,
        port,
        max_clients=options.http_max_clients,
        timeline_offset_s=options.timeline_offset_s,
    )


def load_page() -> bytes:
    """The page as shipped in the package (InputError if the installation lacks it)."""
    try:
        return (
            resources.files(__package__ or "service.output.sinks").joinpath(PAGE_ASSET).read_bytes()
        )
    except OSError as exc:
        raise InputError(f"HTTP status page: the package's {PAGE_ASSET} is missing") from exc


def _csp_hash(page: bytes, tag: str) -> str:
    """``'sha256-...'`` of the text of the page's one inline ``<tag>`` element (CSP 3)."""
    m = re.search(rb"<" + tag.encode() + rb">(.*?)</" + tag.encode() + rb">", page, re.S)
    if m is None:
        raise InputError(f"HTTP status page: {PAGE_ASSET} has no <{tag}>")
    return "'sha256-" + base64.b64encode(hashlib.sha256(m.group(1)).digest()).decode() + "'"


def content_security_policy(page: bytes) -> str:
    """The page's policy: its own inline script and style (by hash), requests to itself."""
    return (
        f"default-src 'none'; script-src {_csp_hash(page, 'script')}; "
        f"style-src {_csp_hash(page, 'style')}; connect-src 'self'; img-src 'self' data:; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    addr: Any
    opened_s: float
    head: bytearray = field(default_factory=bytearray)
    out: deque[bytes] = field(default_factory=deque)
    queued_bytes: int = 0
    sse: bool = False
    closing: bool = False  # close once ``out`` is sent (a plain answer)
    last_sent_s: float = 0.0


class _PageState:
    """What the page shows, kept by the I/O thread from the records."""

    def __init__(self, timeline_offset_s: float) -> None:
        self.latest: dict[str, Mapping[str, Any]] = {}
        self.latest_json: dict[str, bytes] = {}
        self.timeline = Timeline(timeline_offset_s)
        self.history: deque[list[Any]] = deque()  # [t_s, lat_deg, lon_deg, mode]
        self.modes: deque[list[Any]] = deque(maxlen=MODE_CHANGES)  # [tow_s, since_s, mode]
        self._mode = ""

    def take(self, cls: str, rec: Mapping[str, Any]) -> list[bytes]:
        """Update from one record; the SSE events it makes (each record encoded once)."""
        events: list[bytes] = []
        if self.timeline.on_record(cls, rec):
            events.append(_sse("timeline", dumps(self.timeline_view())))
        if cls == "FIX":
            self._fix(rec)
        elif cls == "SKY":
            rec = sky_view(rec)
        elif cls != "STATUS":
            return events
        body = dumps(rec)
        events.append(_sse(cls.lower(), body))
        self.latest[cls] = rec
        self.latest_json[cls] = body.encode()
        return events

    def _fix(self, rec: Mapping[str, Any]) -> None:
        mode = str(rec.get("mode", ""))
        tow = rec.get("gpst_tow_s")
        t_s = _data_time_s(rec)
        if mode != self._mode:
            self._mode = mode
            self.modes.append([tow, rec.get("since_start_s"), mode])
        if t_s is None or "lat_deg" not in rec:
            return
        h = self.history
        if h and t_s < h[-1][0]:  # data time went back (another stream, a restart): anew
            h.clear()
        if not h or t_s - h[-1][0] >= HISTORY_STEP_S - 1e-9:
            h.append([t_s, rec["lat_deg"], rec["lon_deg"], mode])
        while h and t_s - h[0][0] > HISTORY_S:
            h.popleft()

    def timeline_view(self) -> dict[str, Any]:
        figures = self.timeline.figures()
        return {
            "since": "the emulated restart" if self.timeline.restarted else "the first measurement",
            "order": list(ORDER),
            "t_s": figures,
            "text": self.timeline.texts(),
        }

    def snapshot(self) -> dict[str, Any]:
        return {
            "fix": self.latest.get("FIX"),
            "sky": self.latest.get("SKY"),
            "status": self.latest.get("STATUS"),
            "timeline": self.timeline_view(),
            "history": list(self.history),
            "modes": list(self.modes),
            "history_s": HISTORY_S,
        }


def _data_time_s(rec: Mapping[str, Any]) -> float | None:
    week, tow = rec.get("gpst_week"), rec.get("gpst_tow_s")
    if week is None or tow is None:
        return None
    return float(week) * 604800.0 + float(tow)


def sky_view(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A SKY record for the page: each satellite with its ``orbit`` (GEO, IGSO, MEO, or
    ``""`` for another system) and ``system`` (the ID's letter)."""
    sats = [
        {**s, "orbit": orbit_class(str(s.get("prn", ""))), "system": str(s.get("prn", ""))[:1]}
        for s in rec.get("satellites", ())
    ]
    return {**rec, "satellites": sats}


def _sse(name: str, json_text: str) -> bytes:
    return f"event: {name}\ndata: {json_text}\n\n".encode()


class HttpPageServer(Sink):
    """The status page, its event stream and its JSON, from the sink's own thread."""

    records = frozenset(RECORD_CLASSES)

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_clients: int = HTTP_MAX_CLIENTS,
        timeline_offset_s: float = 0.0,
        backlog_bytes: int = CLIENT_BACKLOG_BYTES,
    ) -> None:
        if max_clients < 1:
            raise ConfigError(f"HTTP status page: at most {max_clients} clients: expected >= 1")
        self.max_clients = max_clients
        self.backlog_bytes = backlog_bytes
        self._page = load_page()
        self._csp = content_security_policy(self._page)
        self._counters = Counters()
        self._loopback = is_loopback(host)
        if not self._loopback:
            log.warning("HTTP status page listens on %s:%d, not loopback", host, port)
        self._srv = listening_socket(host, port, LISTEN_BACKLOG, "HTTP status page")
        self.address: tuple[str, int] = self._srv.getsockname()[:2]
        self._state = _PageState(timeline_offset_s)
        self._inbox: deque[tuple[str, Mapping[str, Any]]] = deque(maxlen=INBOX_RECORDS)
        self._woken = False
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._srv, selectors.EVENT_READ, "listen")
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._clients: dict[socket.socket, _Client] = {}
        self._n_clients = 0
        self._n_sse = 0
        self._logged_at = -math.inf
        self._unlogged = 0
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bdsfix-http", daemon=True)
        self._thread.start()
        log.info("status page on http://%s:%d/", *self.address)

    # --- the loop's side: nothing but an append and, at most once per batch, a wake ------
    def write_record(self, cls: str, record: Mapping[str, Any]) -> None:
        if len(self._inbox) == INBOX_RECORDS:
            self._counters.add("http_records_dropped")
        self._inbox.append((cls, record))
        if not self._woken:
            self._woken = True
            self._wake()

    def counters(self) -> Mapping[str, int]:
        return self._counters.snapshot() | {
            "http_clients": self._n_clients,
            "http_event_streams": self._n_sse,
        }

    @property
    def n_event_streams(self) -> int:
        """Browsers (or other readers) on ``/events`` now."""
        return self._n_sse

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # a full wake pipe already means "wake up"
            self._wake_w.send(b"\0")

    # --- the sink's own thread ------------------------------------------------------------
    def _loop(self) -> None:
        next_keepalive = time.monotonic() + KEEPALIVE_S
        while not self._closed.is_set():
            try:
                events = self._sel.select(timeout=1.0)
            except (OSError, ValueError):
                return
            for key, mask in events:
                if key.data == "wake":
                    with contextlib.suppress(OSError):
                        self._wake_r.recv(4096)
                elif key.data == "listen":
                    self._accept()
                else:
                    client: _Client = key.data
                    if mask & selectors.EVENT_READ:
                        self._readable(client)
                    if mask & selectors.EVENT_WRITE and client.sock in self._clients:
                        self._send(client)
            self._publish()
            now = time.monotonic()
            self._expire(now)
            if now >= next_keepalive:
                next_keepalive = now + KEEPALIVE_S
                for c in list(self._clients.values()):
                    if c.sse and now - c.last_sent_s >= KEEPALIVE_S:
                        self._queue(c, b": keepalive\n\n")
        self._publish()  # what the loop wrote last (the final STATUS) ...
        deadline = time.monotonic() + 1.0  # ... to the browsers that read, briefly
        while any(c.out for c in self._clients.values()) and time.monotonic() < deadline:
            for c in list(self._clients.values()):
                self._send(c)
            time.sleep(0.01)

    def _publish(self) -> None:
        """Records from the in-box: the page state, then one block of events per client."""
        self._woken = False
        if not self._inbox:
            return
        chunks: list[bytes] = []
        while self._inbox:
            try:
                cls, rec = self._inbox.popleft()
            except IndexError:
                break
            chunks += self._state.take(cls, rec)
        if not chunks:
            return
        block = b"".join(chunks)
        for c in list(self._clients.values()):
            if c.sse:
                self._queue(c, block)

    def _queue(self, c: _Client, data: bytes) -> None:
        if c.queued_bytes + len(data) > self.backlog_bytes:
            self._counters.add("http_clients_dropped_slow")
            log.warning("status page client %s too slow: dropped", c.addr)
            self._drop(c)
            return
        c.out.append(data)
        c.queued_bytes += len(data)
        self._send(c)

    def _send(self, c: _Client) -> None:
        while c.out:
            chunk = c.out[0]
            try:
                n = c.sock.send(chunk)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._drop(c)
                return
            c.queued_bytes -= n
            c.last_sent_s = time.monotonic()
            if n < len(chunk):
                c.out[0] = chunk[n:]
                break
            c.out.popleft()
        if not c.out and c.closing:
            # the answer is out: end our side and read what the client still sends until it
            # closes (closing with unread bytes would reset the connection, and the client
            # could lose the answer); HEAD_TIMEOUT_S bounds the wait
            with contextlib.suppress(OSError):
                c.sock.shutdown(socket.SHUT_WR)
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if c.out else 0)
        with contextlib.suppress(KeyError, ValueError):
            if self._sel.get_key(c.sock).events != want:
                self._sel.modify(c.sock, want, c)

    def _accept(self) -> None:
        for _ in range(LISTEN_BACKLOG):
            try:
                sock, addr = self._srv.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # EMFILE and the like: the next turn of the loop tries again
            if len(self._clients) >= self.max_clients:
                self._counters.add("http_clients_refused")
                sock.close()
                self._log_rarely(
                    "status page client %s refused: %d connections open, the most allowed "
                    "(http_max_clients)",
                    addr,
                    self.max_clients,
                )
                continue
            sock.setblocking(False)
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, KERNEL_SNDBUF_BYTES)
            c = _Client(sock, addr, time.monotonic())
            self._clients[sock] = c
            self._n_clients = len(self._clients)
            self._sel.register(sock, selectors.EVENT_READ, c)

    def _log_rarely(self, msg: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._logged_at < LOG_EVERY_S:
            self._unlogged += 1
            return
        if self._unlogged:
            msg += f" ({self._unlogged} more since the last report)"
        self._logged_at, self._unlogged = now, 0
        log.warning(msg, *args)

    def _readable(self, c: _Client) -> None:
        try:
            data = c.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:  # the browser closed its end (or reset it)
            self._drop(c)
            return
        if c.sse or c.closing:
            return  # what a client sends once answered is read and ignored
        c.head += data
        end = c.head.find(b"\r\n\r\n")
        if end < 0:
            if len(c.head) > MAX_HEAD_BYTES:
                self._answer(c, 404, b"not found\n", _TEXT)
            return
        if end > MAX_HEAD_BYTES:
            self._answer(c, 404, b"not found\n", _TEXT)
            return
        self._request(c, bytes(c.head[:end]))

    def _request(self, c: _Client, head: bytes) -> None:
        self._counters.add("http_requests")
        lines = head.split(b"\r\n")
        m = _REQUEST_LINE.match(lines[0])
        if m is None:
            self._answer(c, 400, b"bad request\n", _TEXT)
            return
        method, path = m.group(1), m.group(2)  # the whole target: no query is ours either
        if method not in (b"GET", b"HEAD"):
            self._answer(
                c,
                405,
                b"read-only: GET or HEAD\n",
                _TEXT,
                extra=("Allow: GET, HEAD",),
            )
            return
        if not self._host_ok(lines[1:]):
            self._answer(
                c,
                421,
                b"this page answers to a loopback address only\n",
                _TEXT,
            )
            return
        route = path.decode("ascii", "replace")
        if route not in _ROUTES:
            self._counters.add("http_not_found")
            self._answer(c, 404, b"not found\n", _TEXT, head_only=method == b"HEAD")
            return
        head_only = method == b"HEAD"
        if route == "/":
            self._answer(c, 200, self._page, "text/html; charset=utf-8", head_only=head_only)
        elif route == "/events":
            self._start_events(c, head_only)
        else:
            cls = "FIX" if route == "/fix.json" else "STATUS"
            body = self._state.latest_json.get(cls)
            if body is None:
                self._answer(
                    c,
                    503,
                    dumps({"error": f"no {cls} record yet"}).encode() + b"\n",
                    "application/json",
                    head_only=head_only,
                    extra=("Retry-After: 1",),
                )
            else:
                self._answer(c, 200, body + b"\n", "application/json", head_only=head_only)

    def _host_ok(self, header_lines: list[bytes]) -> bool:
        """Listening on loopback: the Host header must name a loopback address or localhost."""
        if not self._loopback:
            return True
        for line in header_lines:
            name, _, value = line.partition(b":")
            if name.strip().lower() != b"host":
                continue
            host = value.strip().decode("ascii", "replace")
            if host.startswith("["):
                host = host[1:].split("]", 1)[0]
            else:
                host = host.rsplit(":", 1)[0] if host.count(":") == 1 else host
            if host.lower() == "localhost":
                return True
            try:
                return ipaddress.ip_address(host).is_loopback
            except ValueError:
                return False
        return True  # HTTP/1.0 without Host: only a local program can have sent it

    def _headers(
        self, status: int, ctype: str, length: int | None, extra: tuple[str, ...]
    ) -> bytes:
        lines = [
            f"HTTP/1.1 {status} {_REASONS[status]}",
            f"Content-Type: {ctype}",
            *([f"Content-Length: {length}"] if length is not None else []),
            f"Content-Security-Policy: {self._csp}",
            "X-Content-Type-Options: nosniff",
            "Referrer-Policy: no-referrer",
            "X-Frame-Options: DENY",
            "Cache-Control: no-store",
            "Cross-Origin-Resource-Policy: same-origin",
            "Cross-Origin-Opener-Policy: same-origin",
            "Connection: close",
            *extra,
        ]
        return ("\r\n".join(lines) + "\r\n\r\n").encode()

    def _answer(
        self,
        c: _Client,
        status: int,
        body: bytes,
        ctype: str,
        head_only: bool = False,
        extra: tuple[str, ...] = (),
    ) -> None:
        c.closing = True
        with contextlib.suppress(KeyError, ValueError):
            self._sel.modify(c.sock, selectors.EVENT_READ, c)
        data = self._headers(status, ctype, len(body), extra) + (b"" if head_only else body)
        c.out.append(data)
        c.queued_bytes += len(data)
        self._send(c)

    def _start_events(self, c: _Client, head_only: bool) -> None:
        head = self._headers(200, "text/event-stream; charset=utf-8", None, ())
        if head_only:
            self._answer(c, 200, b"", "text/event-stream; charset=utf-8", head_only=True)
            return
        c.sse = True
        self._n_sse = sum(1 for x in self._clients.values() if x.sse)
        self._counters.add("http_event_streams_opened")
        self._queue(c, head + b"retry: 2000\n\n" + _sse("state", dumps(self._state.snapshot())))

    def _expire(self, now: float) -> None:
        for c in list(self._clients.values()):
            if not c.sse and now - c.opened_s > HEAD_TIMEOUT_S:
                self._drop(c)

    def _drop(self, c: _Client) -> None:
        if self._clients.pop(c.sock, None) is None:
            return
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(c.sock)
        with contextlib.suppress(OSError):
            c.sock.close()
        c.out.clear()
        self._n_clients = len(self._clients)
        self._n_sse = sum(1 for x in self._clients.values() if x.sse)

    def close(self) -> None:
        """Stop the thread (after a last publish and a brief flush) and close every socket."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._wake()
        self._thread.join(timeout=3)
        for c in list(self._clients.values()):
            self._drop(c)
        self._sel.close()
        for s in (self._srv, self._wake_r, self._wake_w):
            s.close()


__all__ = ["HttpPageServer", "content_security_policy", "load_page", "open_sink", "sky_view"]
