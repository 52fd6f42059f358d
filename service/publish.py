"""Publishers: NMEA 0183 over TCP/serial/file, ZeroMQ PUB JSON, JSONL. None of them blocks.

- :class:`NmeaTcpServer`: a multi-client TCP server in its own thread (selectors). Each
  client has a bounded output buffer; a client that does not read until its buffer
  overflows is dropped and counted, as gpsd does with slow clients.
- :class:`ZmqPublisher`: a PUB socket; each message is two frames, topic (``FIX``, ``SKY``,
  ``TRACK``, ``STATUS``) and a JSON object. Sends use ``NOBLOCK`` with a send high-water
  mark, so a full queue drops (and counts) instead of waiting.
- :class:`LineSink`: a file or stdout, line-buffered, reopened on SIGHUP (log rotation).
- :class:`SerialSink`: a serial device or pty, with a zero write timeout.
Binding to anything but loopback logs a warning: listening elsewhere must be asked for.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import logging
import selectors
import socket
import sys
import threading
from collections import Counter, deque
from collections.abc import Mapping
from typing import IO, Any

from service.constants import C_M_S
from service.errors import ConfigError
from service.nmea import sentences_for_fix
from service.records import dumps, fix_record, sky_record, status_record
from service.timebase import utc_from_gpst

log = logging.getLogger(__name__)


def _is_loopback(host: str) -> bool:
    if host in ("localhost", ""):
        return host == "localhost"
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_host_port(text: str, what: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ConfigError(f"{what} {text!r}: expected HOST:PORT")
    return host.strip("[]") or "127.0.0.1", int(port)


class NmeaTcpServer:
    """NMEA to any number of TCP clients; slow clients are dropped, never waited for."""

    def __init__(
        self, host: str = "127.0.0.1", port: int = 10110, max_buffer_bytes: int = 256 * 1024
    ) -> None:
        self.max_buffer_bytes = max_buffer_bytes
        self.counters: Counter[str] = Counter()
        if not _is_loopback(host):
            log.warning("NMEA TCP server listens on %s:%d, not loopback", host, port)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._srv = socket.socket(family, socket.SOCK_STREAM)
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._srv.bind((host, port))
        except OSError as exc:
            self._srv.close()
            why = "address already in use" if exc.errno == errno.EADDRINUSE else exc.strerror
            raise ConfigError(f"NMEA TCP {host}:{port}: {why}") from exc
        self._srv.listen(16)
        self._srv.setblocking(False)
        self.address: tuple[str, int] = self._srv.getsockname()[:2]
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._srv, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._lock = threading.Lock()
        self._clients: dict[socket.socket, deque[bytes]] = {}
        self._sizes: dict[socket.socket, int] = {}
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bdsfix-nmea-tcp", daemon=True)
        self._thread.start()

    @property
    def n_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, data: bytes) -> None:
        """Queue ``data`` for every client (never blocks)."""
        drop = []
        with self._lock:
            for sock, q in self._clients.items():
                if self._sizes[sock] + len(data) > self.max_buffer_bytes:
                    drop.append(sock)
                    continue
                q.append(data)
                self._sizes[sock] += len(data)
        for sock in drop:
            self.counters["nmea_clients_dropped_slow"] += 1
            log.warning("NMEA client %s too slow: dropped", _peer(sock))
            self._drop(sock)
        with contextlib.suppress(BlockingIOError, OSError):
            self._wake_w.send(b"\0")

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            self._clients.pop(sock, None)
            self._sizes.pop(sock, None)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(sock)
        sock.close()

    def _loop(self) -> None:
        while not self._closed.is_set():
            try:
                events = self._sel.select(timeout=0.5)
            except (OSError, ValueError):
                return
            for key, _mask in events:
                if key.data == "wake":
                    with contextlib.suppress(BlockingIOError, OSError):
                        self._wake_r.recv(4096)
                elif key.fileobj is self._srv:
                    self._accept()
                else:
                    self._readable(key.fileobj)  # type: ignore[arg-type]
            self._flush()

    def _accept(self) -> None:
        try:
            sock, addr = self._srv.accept()
        except OSError:
            return
        sock.setblocking(False)
        with self._lock:
            self._clients[sock] = deque()
            self._sizes[sock] = 0
        self._sel.register(sock, selectors.EVENT_READ, "client")
        self.counters["nmea_clients_accepted"] += 1
        log.info("NMEA client %s connected", addr)

    def _readable(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(4096)  # clients may send ?WATCH etc.: read and ignore
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(sock)

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
                    self._drop(sock)
                    break
                with self._lock:
                    self._sizes[sock] = self._sizes.get(sock, 0) - n
                if n < len(chunk):
                    q[0] = chunk[n:]
                    break
                q.popleft()

    def close(self) -> None:
        self._closed.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")
        self._thread.join(timeout=2)
        with self._lock:
            socks = list(self._clients)
        for s in socks:
            self._drop(s)
        self._sel.close()
        for s in (self._srv, self._wake_r, self._wake_w):
            s.close()


def _peer(sock: socket.socket) -> str:
    try:
        return str(sock.getpeername())
    except OSError:
        return "?"


class ZmqPublisher:
    """ZeroMQ PUB socket: [topic, JSON] messages, dropped (and counted) when queues are full."""

    def __init__(
        self,
        endpoint: str = "tcp://127.0.0.1:10111",
        sndhwm: int = 1000,
        curve_secret_key: bytes | None = None,
        curve_public_key: bytes | None = None,
    ) -> None:
        import zmq

        self._zmq = zmq
        self.counters: Counter[str] = Counter()
        host = endpoint.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]")
        if endpoint.startswith("tcp://") and not _is_loopback(host):
            log.warning("ZeroMQ PUB binds %s, not loopback", endpoint)
        self._ctx: Any = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.SNDHWM, sndhwm)
        self._sock.setsockopt(zmq.LINGER, 100)
        if curve_secret_key is not None:
            self._sock.curve_secretkey = curve_secret_key
            self._sock.curve_publickey = curve_public_key
            self._sock.curve_server = True
        try:
            self._sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self._sock.close(0)
            raise ConfigError(f"ZeroMQ {endpoint}: {exc}") from exc
        self.endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)

    def send(self, topic: str, record: Mapping[str, Any]) -> bool:
        try:
            self._sock.send_multipart(
                [topic.encode(), dumps(record).encode()], flags=self._zmq.NOBLOCK
            )
        except self._zmq.Again:
            self.counters["zmq_dropped"] += 1
            return False
        self.counters[f"zmq_{topic}"] += 1
        return True

    def close(self) -> None:
        self._sock.close(linger=100)


class LineSink:
    """Lines to a file or ``-`` (stdout); :meth:`reopen` appends to a (rotated) file anew."""

    def __init__(self, target: str, append: bool = False) -> None:
        self.target = target
        self._fh: IO[str] | None = None
        self._open("a" if append else "w")

    def reopen(self) -> None:
        self._open("a")

    def _open(self, mode: str) -> None:
        if self.target == "-":
            self._fh = sys.stdout
            return
        old = self._fh
        try:
            self._fh = open(self.target, mode, encoding="ascii", buffering=1)  # noqa: SIM115
        except OSError as exc:
            raise ConfigError(f"cannot write {self.target}: {exc.strerror}") from exc
        if old is not None:
            old.close()

    def write(self, text: str) -> None:
        if self._fh is not None:
            self._fh.write(text)

    def close(self) -> None:
        if self._fh is not None and self._fh is not sys.stdout:
            self._fh.close()
        self._fh = None


class SerialSink:
    """NMEA to a serial device or pty; bytes that cannot go out at once are dropped."""

    def __init__(self, device: str, baud: int = 115200) -> None:
        import serial

        self.counters: Counter[str] = Counter()
        try:
            self._port = serial.Serial(device, baud, write_timeout=0)
        except serial.SerialException as exc:
            raise ConfigError(f"NMEA serial {device}: {exc}") from exc

    def write(self, data: bytes) -> None:
        import serial

        try:
            self._port.write(data)
        except serial.SerialTimeoutException:
            self.counters["nmea_serial_dropped"] += 1
        except serial.SerialException as exc:
            self.counters["nmea_serial_errors"] += 1
            log.warning("NMEA serial write failed: %s", exc)

    def close(self) -> None:
        self._port.close()


class Publishers:
    """Fan-out of epoch results, TRACK and STATUS to the configured outputs."""

    def __init__(
        self,
        *,
        nmea_tcp: NmeaTcpServer | None = None,
        nmea_lines: LineSink | None = None,
        nmea_serial: SerialSink | None = None,
        zmq: ZmqPublisher | None = None,
        jsonl: LineSink | None = None,
        talker: str = "GN",
    ) -> None:
        self.nmea_tcp = nmea_tcp
        self.nmea_lines = nmea_lines
        self.nmea_serial = nmea_serial
        self.zmq = zmq
        self.jsonl = jsonl
        self.talker = talker
        self.counters: Counter[str] = Counter()
        self._time_known = False

    def epoch(self, result: Any) -> None:
        fix = result.fix
        self.counters[f"published_{fix.mode}"] += 1
        if fix.ok:
            self._time_known = True
        rec = fix_record(fix, result.since_start_s)
        if self.jsonl is not None:
            self.jsonl.write(dumps(rec) + "\n")
        if self.zmq is not None:
            self.zmq.send("FIX", rec)
            if fix.sky:
                self.zmq.send("SKY", sky_record(fix.gpst_week, fix.gpst_tow_s, fix.sky))
        if self.nmea_tcp or self.nmea_lines or self.nmea_serial:
            # the fix's own time: receiver time tag minus the solved clock bias
            tow = fix.gpst_tow_s - (fix.clock_bias_m or 0.0) / C_M_S
            utc = utc_from_gpst(fix.gpst_week, tow)
            data = b"".join(
                sentences_for_fix(fix, utc=utc, talker=self.talker, time_known=self._time_known)
            )
            if self.nmea_tcp is not None:
                self.nmea_tcp.publish(data)
            if self.nmea_lines is not None:
                self.nmea_lines.write(data.decode("ascii"))
            if self.nmea_serial is not None:
                self.nmea_serial.write(data)

    def track(self, event: Any) -> None:
        rec = {
            "class": "TRACK",
            "prn": event.prn,
            "event": event.event,
            "nav_type": event.nav_type,
            "gpst_week": event.gpst_week,
            "gpst_tow_s": round(event.gpst_tow_s, 6),
            "since_start_s": round(event.since_start_s, 6),
        }
        if event.sow_s is not None:
            rec["sow_s"] = event.sow_s
        if self.zmq is not None:
            self.zmq.send("TRACK", rec)
        if self.jsonl is not None:
            self.jsonl.write(dumps(rec) + "\n")

    def status(self, counters: Mapping[str, int | float]) -> None:
        merged: Counter[str] = Counter()
        merged.update(dict(counters))
        merged.update(self.counters)
        for part in (self.nmea_tcp, self.zmq, self.nmea_serial):
            if part is not None:
                merged.update(part.counters)
        if self.nmea_tcp is not None:
            merged["nmea_clients"] = self.nmea_tcp.n_clients
        if self.zmq is not None:
            self.zmq.send("STATUS", status_record(merged))

    def reopen(self) -> None:
        for sink in (self.nmea_lines, self.jsonl):
            if sink is not None:
                sink.reopen()

    def close(self) -> None:
        for part in (self.nmea_tcp, self.zmq, self.nmea_serial, self.nmea_lines, self.jsonl):
            if part is not None:
                part.close()
