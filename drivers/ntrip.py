"""An NTRIP client as a byte transport: the RTCM 3 stream of one caster mountpoint.

Reference: RTCM 10410.1 (NTRIP v2.0, section 3: HTTP/1.1 ``GET /MOUNT`` with
``Ntrip-Version: Ntrip/2.0`` and Basic authentication; a v1 caster answers ``ICY 200 OK``,
a v2 caster ``HTTP/1.1 200 OK``, possibly with ``Transfer-Encoding: chunked`` (RFC 9112
section 7.1); a caster that does not know the mountpoint answers with its source table,
``SOURCETABLE 200 OK`` or ``Content-Type: gnss/sourcetable``).

The bytes go through the same :class:`~drivers.source.StreamDecoder` as a receiver's
(:func:`open_ntrip`), so RTCM 1042 becomes :class:`~service.core.types.Ephemeris` events.

Why not pygnssutils' ``GNSSNTRIPClient`` (1.3.1): tried against its own caster on loopback,
it does not fit a daemon. When the caster goes away its reader thread spins on the closed
socket, putting ``(b"", None)`` on the output queue (567,000 items in 4 s) and never notices
the loss; its retry count is never reset, so it gives up for good after ``retries`` outages
in the life of the process; it logs the request's ``Authorization`` header (the credentials
in base64) at DEBUG; and each instance adds its own stderr handler to the ``pyrtcm`` logger.
This transport reuses the reconnecting base of :mod:`drivers.transport` (backoff, counters,
one WARNING per outage) and is about a hundred lines.

Behaviour:

- connection refused, reset, closed by the caster, or no byte for :data:`IDLE_S`: reconnect
  with exponential backoff (``backoff_initial_s`` doubling to ``backoff_max_s``); the
  backoff is reset only once a connection has brought a whole RTCM 3 frame (CRC-24Q
  checked, RTCM 10403.3 section 4.2), not at each answer, so a caster that answers 200 and
  closes, or sends a bad chunk size, is tried every ``backoff_max_s``, with a log line a
  minute (``drops_before_data``, see :class:`drivers.transport._Reconnecting`);
- the answer's header must be whole within ``header_timeout_s`` (:data:`HEADER_TIMEOUT_S`),
  however slowly it trickles in, or the attempt fails (``header_timeouts``; the first
  failure of an outage is a WARNING), so a caster sending its header a byte a second cannot
  hold network ephemerides for hours;
- a connection that brings :data:`NO_RTCM_BYTES` bytes, or ends, without one RTCM 3 frame is
  counted ``no_rtcm_streams``; the first such stream is logged once at INFO (is the
  mountpoint an RTCM 3 stream?): the framer's per-byte resync lines stay at DEBUG,
  rate-limited;
- HTTP 401/403 (credentials refused), 404 or a source table (no such mountpoint), any other
  4xx: :class:`NtripRefusedError`, not retried (casters block addresses that retry bad
  credentials); 5xx and malformed answers are retried;
- the transport's name, its log lines and its errors show the URL redacted
  (:meth:`~service.core.ntripurl.NtripUrl.redacted`): never the user or the password.

Counter keys (with those of :mod:`drivers.transport` and :class:`~drivers.source.StreamDecoder`;
the daemon's STATUS shows them with the prefix ``ntrip_``): ``refused``, ``http_errors``,
``header_timeouts``, ``no_rtcm_streams``.
"""

from __future__ import annotations

import logging
import re
import socket
import time
from typing import Any

from drivers.framing import NEED_MORE
from drivers.rtcm import FRAMING as RTCM_FRAMING
from drivers.rtcm import MAX_PAYLOAD as RTCM_MAX_PAYLOAD
from drivers.rtcm import PREAMBLE as RTCM_PREAMBLE
from drivers.source import BinarySource, StreamDecoder
from drivers.transport import _Reconnecting
from service.core.errors import InputError
from service.core.ntripurl import NtripUrl

log = logging.getLogger(__name__)

USER_AGENT = "NTRIP bdsfix/0.1"
ICY_OK = b"ICY 200 OK\r\n"
MAX_HEADER_BYTES = 16384
IDLE_S = 60.0
"""A connection that brings no byte for this long is dropped and reopened [s]."""
RECONNECT_MAX_S = 4.0
"""Default longest wait between two attempts to reach the caster [s]."""
HEADER_TIMEOUT_S = 10.0
"""Default longest time for the caster's whole answer header [s]."""
NO_RTCM_BYTES = 65536
"""Body bytes without one RTCM 3 frame after which a stream is judged not RTCM 3."""


_CHUNK_SIZE = re.compile(rb"[0-9A-Fa-f]{1,15}")
"""A chunk size (RFC 9112 section 7.1: ``1*HEXDIG``; 15 digits bound it below 2**60)."""


class NtripRefusedError(InputError):
    """The caster refused the request for good: credentials, mountpoint or another 4xx."""


class ChunkDecoder:
    """Incremental decoder of HTTP/1.1 chunked transfer coding (RFC 9112 section 7.1):
    ``feed(bytes) -> body bytes``, whatever the split of the input; ``done`` after the last
    (zero-size) chunk. Chunk extensions and trailers are skipped."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._left = 0  # body bytes left in the current chunk
        self._need_crlf = False  # the CRLF that ends a chunk's data
        self.done = False

    def feed(self, data: bytes) -> bytes:
        self._buf += data
        out = bytearray()
        while not self.done:
            if self._left:
                take = self._buf[: self._left]
                out += take
                del self._buf[: len(take)]
                self._left -= len(take)
                if self._left:
                    break
                self._need_crlf = True
            if self._need_crlf:
                if len(self._buf) < 2:
                    break
                if self._buf[:2] != b"\r\n":
                    raise ValueError("chunked body: no CRLF after a chunk")
                del self._buf[:2]
                self._need_crlf = False
            end = self._buf.find(b"\r\n")
            if end < 0:
                if len(self._buf) > 1024:
                    raise ValueError("chunked body: chunk size line too long")
                break
            size_text = bytes(self._buf[:end]).split(b";", 1)[0].strip()
            # chunk-size = 1*HEXDIG: not int(x, 16), which takes "-5", "+5", "0x5" and "5_0"
            if not _CHUNK_SIZE.fullmatch(size_text):
                raise ValueError(f"chunked body: bad chunk size {size_text[:16]!r}")
            size = int(size_text, 16)
            del self._buf[: end + 2]
            if size == 0:
                self.done = True
                break
            self._left = size
        return bytes(out)


class RtcmFrameSeen:
    """Whether a byte stream has held one whole RTCM 3 frame (preamble, length, CRC-24Q:
    RTCM 10403.3 section 4.2, measured by :data:`drivers.rtcm.FRAMING`): ``feed(bytes)``
    returns True from the first frame on, whatever the split; memory is bounded by one
    frame."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.seen = False

    def feed(self, data: bytes) -> bool:
        if self.seen:
            return True
        self._buf += data
        pos = 0
        while True:
            pos = self._buf.find(RTCM_PREAMBLE, pos)
            if pos < 0:
                self._buf.clear()
                return False
            size = RTCM_FRAMING.measure(self._buf, pos, RTCM_MAX_PAYLOAD)
            if size == NEED_MORE:
                del self._buf[:pos]
                return False
            if size > 0:
                self.seen = True
                self._buf.clear()
                return True
            pos += 1


class NtripTransport(_Reconnecting):
    """The RTCM stream of one NTRIP mountpoint (see the module), reconnecting on loss."""

    confirm_by_data = True

    def __init__(
        self,
        url: NtripUrl,
        *,
        timeout_s: float = 0.1,
        connect_timeout_s: float = 5.0,
        idle_s: float = IDLE_S,
        header_timeout_s: float = HEADER_TIMEOUT_S,
        backoff_initial_s: float = 0.25,
        backoff_max_s: float = RECONNECT_MAX_S,
    ) -> None:
        super().__init__(
            url.redacted(),
            timeout_s=timeout_s,
            backoff_initial_s=min(backoff_initial_s, backoff_max_s),
            backoff_max_s=backoff_max_s,
        )
        self.url = url
        self.connect_timeout_s = connect_timeout_s
        self.idle_s = idle_s
        self.header_timeout_s = header_timeout_s
        self._sock: socket.socket | None = None
        self._frames = RtcmFrameSeen()  # of the current connection
        self._body_bytes = 0  # of the current connection
        self._no_rtcm_judged = False  # the current connection counted as no RTCM
        self._no_rtcm_logged = False
        self._pending = b""  # body bytes that came with the response header
        self._chunks: ChunkDecoder | None = None
        self._last_byte = 0.0

    def request(self) -> bytes:
        """The HTTP request for the mountpoint (RTCM 10410.1 v2; v1 casters accept it)."""
        host = f"[{self.url.host}]" if ":" in self.url.host else self.url.host
        lines = [
            f"GET /{self.url.mount} HTTP/1.1",
            f"Host: {host}:{self.url.port}",
            "Ntrip-Version: Ntrip/2.0",
            f"User-Agent: {USER_AGENT}",
        ]
        auth = self.url.authorization()
        if auth is not None:
            lines.append(f"Authorization: {auth}")
        lines += ["Accept: */*", "Connection: close", "", ""]
        return "\r\n".join(lines).encode("ascii")

    def _handle(self) -> Any:
        return self._sock

    def _connect(self) -> None:
        sock = socket.create_connection(
            (self.url.host, self.url.port), timeout=self.connect_timeout_s
        )
        try:
            sock.sendall(self.request())
            body = self._read_response(sock)
        except BaseException:
            sock.close()
            raise
        sock.settimeout(self.timeout_s)
        self._sock = sock
        self._pending = body
        self._last_byte = time.monotonic()
        self._frames = RtcmFrameSeen()
        self._body_bytes = 0
        self._no_rtcm_judged = False

    def _read_response(self, sock: socket.socket) -> bytes:
        """Read and judge the response header; returns the body bytes that came with it.

        The whole header must come within ``header_timeout_s`` (TimeoutError otherwise,
        counted ``header_timeouts``), however it trickles in."""
        buf = b""
        deadline = time.monotonic() + self.header_timeout_s
        while True:
            if buf.startswith(ICY_OK):
                # NTRIP v1: the data follow the status line, after an empty line or not
                # (RTCM 3 starts with 0xD3, never CR): wait until that is decided.
                rest = buf[len(ICY_OK) :]
                if len(rest) >= 2 or not b"\r\n".startswith(rest):
                    self._chunks = None
                    return rest.removeprefix(b"\r\n")
            head, sep, rest = buf.partition(b"\r\n\r\n")
            if sep:
                break
            if len(buf) > MAX_HEADER_BYTES:
                raise ConnectionError("the caster's answer has no end of header")
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                self.counters["header_timeouts"] += 1
                raise TimeoutError(
                    f"no whole answer header within {self.header_timeout_s:g} s "
                    f"({len(buf)} bytes of it)"
                )
            sock.settimeout(min(self.connect_timeout_s, left_s))
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue  # the deadline above decides
            if not data:
                raise ConnectionError(
                    "the caster closed the connection before answering"
                    if not buf
                    else "the caster closed the connection in its answer"
                )
            buf += data
        lines = head.decode("latin-1").split("\r\n")
        status = lines[0].split()
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, colon, value = line.partition(":")
            if colon:
                headers[name.strip().lower()] = value.strip()
        if len(status) < 2 or not status[1].isdigit():
            raise ConnectionError(f"not an NTRIP answer: {lines[0][:60]!r}")
        code = int(status[1])
        proto = status[0].upper()
        sourcetable = proto == "SOURCETABLE" or "sourcetable" in headers.get("content-type", "")
        if code in (401, 403):
            self.counters["refused"] += 1
            raise NtripRefusedError(
                f"nav {self.name}: the caster refused the credentials (HTTP {code}); no "
                "network ephemerides until the user and password in 'nav' are fixed and "
                "bdsfix is restarted"
            )
        if code == 404 or (code == 200 and sourcetable):
            self.counters["refused"] += 1
            raise NtripRefusedError(
                f"nav {self.name}: the caster has no mountpoint {self.url.mount!r} (it "
                "answered with its source table); no network ephemerides until 'nav' names "
                "one of its mountpoints and bdsfix is restarted"
            )
        if 400 <= code < 500:
            self.counters["refused"] += 1
            raise NtripRefusedError(
                f"nav {self.name}: the caster refused the request (HTTP {code})"
            )
        if code != 200:
            self.counters["http_errors"] += 1
            raise ConnectionError(f"the caster answered HTTP {code}")
        chunked = "chunked" in headers.get("transfer-encoding", "").lower()
        self._chunks = ChunkDecoder() if chunked else None
        return rest

    def _read_now(self, max_bytes: int) -> bytes:
        if self._sock is None:
            raise ConnectionResetError("not connected")
        if self._pending:
            data, self._pending = self._pending, b""
        else:
            try:
                data = self._sock.recv(max_bytes)
            except TimeoutError:
                if time.monotonic() - self._last_byte > self.idle_s:
                    raise TimeoutError(f"no byte from the caster for {self.idle_s:g} s") from None
                return b""
            if not data:
                raise ConnectionResetError("connection closed by the caster")
        self._last_byte = time.monotonic()
        if self._chunks is not None:
            try:
                data = self._chunks.feed(data)
            except ValueError as err:
                raise ConnectionResetError(str(err)) from err
            if self._chunks.done:
                self._pending = b""
                if data:
                    self._judge_body(data)
                    return data
                raise ConnectionResetError("the caster ended the stream")
        self._judge_body(data)
        return data

    def _judge_body(self, data: bytes) -> None:
        """Confirm the connection at its first whole RTCM 3 frame (see the module)."""
        if self._healthy or not data:
            return
        self._body_bytes += len(data)
        if self._frames.feed(data):
            self._confirmed()
        elif self._body_bytes >= NO_RTCM_BYTES:
            self._no_rtcm()

    def _no_rtcm(self) -> None:
        """The current connection brought bytes and no RTCM 3 frame: counted, logged once."""
        if self._no_rtcm_judged:
            return
        self._no_rtcm_judged = True
        self.counters["no_rtcm_streams"] += 1
        if not self._no_rtcm_logged:
            self._no_rtcm_logged = True
            log.info(
                "nav %s: the caster sends no RTCM 3 (%d bytes and not one frame); is %r an "
                "RTCM 3 mountpoint? (counted no_rtcm_streams; retried)",
                self.name,
                self._body_bytes,
                self.url.mount,
            )

    def _release(self) -> None:
        if self._body_bytes and not self._healthy and not self._closed:
            self._no_rtcm()
        self._body_bytes = 0
        sock, self._sock = self._sock, None
        self._pending = b""
        self._chunks = None
        if sock is not None:
            sock.close()


def open_ntrip(
    url: NtripUrl,
    *,
    reconnect_max_s: float = RECONNECT_MAX_S,
    idle_s: float = IDLE_S,
    header_timeout_s: float = HEADER_TIMEOUT_S,
    gps_week: int | None = None,
) -> BinarySource:
    """Events (ephemerides, and whatever else the mountpoint carries) of an NTRIP source."""
    transport = NtripTransport(
        url, backoff_max_s=reconnect_max_s, idle_s=idle_s, header_timeout_s=header_timeout_s
    )
    return BinarySource(transport, StreamDecoder(gps_week=gps_week))
