"""Publishers: NMEA 0183 over TCP/serial/file, ZeroMQ PUB JSON, JSONL. None of them blocks.

- :class:`NmeaTcpServer`: a multi-client TCP server in its own thread (selectors). Each
  client has a bounded output buffer (and a 64 KiB kernel send buffer); a client that
  does not read until its buffer overflows is dropped and counted
  (``nmea_clients_dropped_slow``), as gpsd does with slow clients. Whatever clients
  send (gpsd's ``?WATCH`` etc.) is read and ignored.
- :class:`ZmqPublisher`: a PUB socket. Framing: each message is two frames,
  ``[topic, body]``: the topic is the record's class in ASCII (``FIX``, ``SKY``,
  ``TRACK``, ``STATUS``), so a SUB socket filters with ``setsockopt(SUBSCRIBE, b"FIX")``;
  the body is the record as compact UTF-8 JSON (see :mod:`service.output.records`). Sends use
  ``NOBLOCK``; a send the socket refuses (EAGAIN) is dropped and counted
  (``zmq_dropped``). Note that libzmq's PUB itself drops, silently and per subscriber,
  messages for a subscriber whose queue has reached the high-water mark (``sndhwm``); the
  sender never sees those drops, so they are not in the counters.
- :class:`LineSink`: a file or ``-`` (stdout), line-buffered; :meth:`LineSink.reopen`
  opens the path anew after logrotate renamed the file (SIGHUP).
- :class:`SerialSink`: a serial device or pty, written by its own thread; the caller only
  queues bytes, and whole payloads that would overflow the bounded queue are dropped and
  counted, so a stalled port never blocks the caller nor receives half a sentence.
- :class:`Publishers`: the fan-out the receiver loop talks to.

Binding to anything but loopback logs a warning: listening elsewhere must be asked for.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import logging
import os
import selectors
import socket
import sys
import threading
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import IO, Any

from service.core.constants import C_M_S
from service.core.errors import ConfigError
from service.core.timebase import utc_from_gpst
from service.core.types import Fix, SatView
from service.output.nmea import gga_sentence, sentences_after_gga
from service.output.records import dumps, fix_record, sky_record, status_record, track_record_of

log = logging.getLogger(__name__)


def _is_loopback(host: str) -> bool:
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


class _Counters:
    """A Counter shared by two threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._c: Counter[str] = Counter()

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._c[key] += n

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._c)

    def __getitem__(self, key: str) -> int:
        with self._lock:
            return self._c[key]


class NmeaTcpServer:
    """NMEA to any number of TCP clients; slow clients are dropped, never waited for.

    ``publish`` only appends to per-client queues under a lock and wakes the I/O thread,
    which accepts, writes whatever each socket takes and closes dropped clients.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = 10110, max_buffer_bytes: int = 256 * 1024
    ) -> None:
        self.max_buffer_bytes = max_buffer_bytes
        self.kernel_sndbuf_bytes = 64 * 1024
        self._counters = _Counters()
        if not _is_loopback(host):
            log.warning("NMEA TCP server listens on %s:%d, not loopback", host, port)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._srv = socket.socket(family, socket.SOCK_STREAM)
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._srv.bind((host, port))
            self._srv.listen(16)
        except OSError as exc:
            self._srv.close()
            why = "address already in use" if exc.errno == errno.EADDRINUSE else exc.strerror
            raise ConfigError(f"NMEA TCP {host}:{port}: {why}") from exc
        self._srv.setblocking(False)
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
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bdsfix-nmea-tcp", daemon=True)
        self._thread.start()

    @property
    def counters(self) -> dict[str, int]:
        return self._counters.snapshot()

    @property
    def n_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, data: bytes) -> None:
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
            try:
                events = self._sel.select(timeout=0.5)
            except (OSError, ValueError):
                return
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
        try:
            sock, addr = self._srv.accept()
        except OSError:
            return
        sock.setblocking(False)
        # a bounded kernel send buffer, so a client that never reads is found (and dropped)
        # once our own max_buffer_bytes fills, instead of after megabytes of autotuning
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.kernel_sndbuf_bytes)
        with self._lock:
            self._clients[sock] = deque()
            self._sizes[sock] = 0
        self._sel.register(sock, selectors.EVENT_READ, "client")
        self._counters.add("nmea_clients_accepted")
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


class ZmqPublisher:
    """ZeroMQ PUB socket sending ``[topic, JSON]`` messages without ever waiting.

    CURVE (optional): ``curve_secret_key_file`` is the server's secret certificate
    (``zmq.auth.create_certificates`` format); subscribers must then know the server's
    public key. ``curve_clients_dir`` holds the public certificates of the subscribers
    allowed in; without it any client that knows the server key may connect. Clients
    refused by the handshake or the ZAP authenticator receive nothing.
    """

    def __init__(
        self,
        endpoint: str = "tcp://127.0.0.1:10111",
        sndhwm: int = 1000,
        linger_ms: int = 100,
        curve_secret_key_file: str = "",
        curve_clients_dir: str = "",
    ) -> None:
        import zmq

        self._zmq = zmq
        self.counters: Counter[str] = Counter()
        host = endpoint.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]")
        if endpoint.startswith("tcp://") and not _is_loopback(host):
            log.warning("ZeroMQ PUB binds %s, not loopback", endpoint)
        self._auth: Any = None
        self._own_ctx = bool(curve_secret_key_file)
        # CURVE: a context of our own, so its ZAP authenticator serves this socket only
        self._ctx: Any = zmq.Context() if self._own_ctx else zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.SNDHWM, sndhwm)
        self._sock.setsockopt(zmq.LINGER, linger_ms)
        self._linger_ms = linger_ms
        try:
            if curve_secret_key_file:
                self._setup_curve(curve_secret_key_file, curve_clients_dir)
            self._sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self.close(linger_ms=0)
            raise ConfigError(f"ZeroMQ {endpoint}: {exc}") from exc
        except ConfigError:
            self.close(linger_ms=0)
            raise
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)

    def _setup_curve(self, secret_file: str, clients_dir: str) -> None:
        import zmq.auth
        from zmq.auth.thread import ThreadAuthenticator

        try:
            public, secret = zmq.auth.load_certificate(secret_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"ZeroMQ CURVE secret key {secret_file}: {exc}") from exc
        if not secret:
            raise ConfigError(f"ZeroMQ CURVE secret key {secret_file}: no secret-key in file")
        if clients_dir and not Path(clients_dir).is_dir():
            raise ConfigError(f"ZeroMQ CURVE clients {clients_dir}: not a directory")
        self._auth = ThreadAuthenticator(self._ctx, log=log)
        self._auth.start()
        if clients_dir:
            self._auth.configure_curve(domain="*", location=clients_dir)
            log.info("ZeroMQ CURVE: clients allowed from %s", clients_dir)
        else:
            self._auth.configure_curve(domain="*", location=self._zmq.auth.CURVE_ALLOW_ANY)
            log.info("ZeroMQ CURVE: any client that knows the server key")
        self._sock.curve_secretkey = secret
        self._sock.curve_publickey = public
        self._sock.curve_server = True

    def send(self, topic: str, record: Mapping[str, Any]) -> bool:
        """Send ``[topic, JSON]``; False (and counted) when the socket refuses it."""
        try:
            self._sock.send_multipart(
                [topic.encode("ascii"), dumps(record).encode("utf-8")], flags=self._zmq.NOBLOCK
            )
        except self._zmq.Again:
            self.counters["zmq_dropped"] += 1
            return False
        except self._zmq.ZMQError as exc:
            self.counters["zmq_errors"] += 1
            log.warning("ZeroMQ send failed: %s", exc)
            return False
        self.counters[f"zmq_{topic}"] += 1
        return True

    def close(self, linger_ms: int | None = None) -> None:
        self._sock.close(linger=self._linger_ms if linger_ms is None else linger_ms)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._own_ctx:
            self._ctx.term()
            self._own_ctx = False


class LineSink:
    """Text lines to a file or ``-`` (stdout), line-buffered.

    :meth:`reopen` opens the path again in append mode, so after logrotate renamed the
    file, new lines go to a fresh file at the configured path. Write errors (disk full)
    are counted and logged once, never raised into the receiver loop.
    """

    def __init__(self, target: str, append: bool = False) -> None:
        self.target = target
        self.counters: Counter[str] = Counter()
        self.reader_gone = False  # a pipe whose reader closed it (EPIPE)
        self._fh: IO[str] | None = None
        self._failing = False
        self._open("a" if append else "w")

    def reopen(self) -> None:
        self._open("a")

    def _open(self, mode: str) -> None:
        if self.target == "-":
            self._fh = sys.stdout
            return
        old = self._fh
        try:
            self._fh = open(self.target, mode, encoding="utf-8", buffering=1)  # noqa: SIM115
        except OSError as exc:
            raise ConfigError(f"cannot write {self.target}: {exc.strerror}") from exc
        if old is not None:
            with contextlib.suppress(OSError):
                old.close()
        self._failing = False

    def write(self, text: str) -> None:
        if self._fh is None or self.reader_gone:
            return
        try:
            self._fh.write(text)
        except BrokenPipeError:
            # a pipe (stdout, a FIFO) whose reader has left, as in `bdsfix replay | head`
            self.reader_gone = True
            self.counters["line_write_errors"] += 1
            log.info("%s: the reader closed the pipe; nothing more is written there", self.target)
            if self._fh is sys.stdout:  # no second EPIPE when Python flushes it at exit
                with contextlib.suppress(OSError, ValueError):
                    null = os.open(os.devnull, os.O_WRONLY)
                    os.dup2(null, sys.stdout.fileno())
                    os.close(null)
        except OSError as exc:
            self.counters["line_write_errors"] += 1
            if not self._failing:
                log.warning("cannot write %s: %s", self.target, exc.strerror)
            self._failing = True
        else:
            self._failing = False

    def close(self) -> None:
        if self._fh is not None and self._fh is not sys.stdout:
            with contextlib.suppress(OSError):
                self._fh.close()
        self._fh = None


class SerialSink:
    """NMEA to a serial device or pty through a writer thread and a bounded queue.

    ``write`` never blocks: a payload that does not fit in ``max_pending_bytes`` is dropped
    whole (``nmea_serial_dropped``), so the port only ever carries complete sentences.
    A port that fails (device unplugged) is counted and logged; later payloads are dropped.
    """

    def __init__(self, device: str, baud: int = 115200, max_pending_bytes: int = 16 * 1024):
        import serial

        self._serial = serial
        self.device = device
        self.max_pending_bytes = max_pending_bytes
        self._counters = _Counters()
        try:
            self._port = serial.Serial(device, baud, write_timeout=None)
        except (serial.SerialException, OSError) as exc:
            raise ConfigError(f"NMEA serial {device}: {exc}") from exc
        self._cond = threading.Condition()
        self._queue: deque[bytes] = deque()
        self._pending = 0
        self._closed = False
        self._failed = False
        self._thread = threading.Thread(target=self._writer, name="bdsfix-nmea-serial", daemon=True)
        self._thread.start()

    @property
    def counters(self) -> dict[str, int]:
        return self._counters.snapshot()

    @property
    def pending_bytes(self) -> int:
        with self._cond:
            return self._pending

    def write(self, data: bytes) -> None:
        with self._cond:
            if self._closed or self._failed or self._pending + len(data) > self.max_pending_bytes:
                self._counters.add("nmea_serial_dropped")
                return
            self._queue.append(data)
            self._pending += len(data)
            self._cond.notify()

    def _writer(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                chunk = self._queue[0]
            try:
                self._port.write(chunk)  # blocks this thread only; close() cancels it
            except (self._serial.SerialException, OSError) as exc:
                with self._cond:
                    if self._closed:
                        return
                    self._failed = True
                    self._queue.clear()
                    self._pending = 0
                self._counters.add("nmea_serial_errors")
                log.warning("NMEA serial %s failed: %s", self.device, exc)
                return
            with self._cond:
                if self._queue and self._queue[0] is chunk:
                    self._queue.popleft()
                    self._pending -= len(chunk)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        with contextlib.suppress(Exception):
            self._port.cancel_write()
        self._thread.join(timeout=2)
        with contextlib.suppress(Exception):
            self._port.close()


class Publishers:
    """Fan-out of fixes, SKY, TRACK and STATUS to the configured outputs.

    FIX goes to JSONL, ZeroMQ and NMEA (all NMEA sinks); SKY to ZeroMQ (and to the NMEA
    GSV of the fix carrying it); TRACK to ZeroMQ and JSONL; STATUS to ZeroMQ. NMEA time is
    the fix's own time: the receiver's time tag minus the solved clock bias.
    """

    def __init__(
        self,
        *,
        nmea_tcp: NmeaTcpServer | None = None,
        nmea_lines: LineSink | None = None,
        nmea_serial: SerialSink | None = None,
        zmq: ZmqPublisher | None = None,
        jsonl: LineSink | None = None,
        talker: str = "GN",
        gsa_talker: str | None = None,
    ) -> None:
        self.nmea_tcp = nmea_tcp
        self.nmea_lines = nmea_lines
        self.nmea_serial = nmea_serial
        self.zmq = zmq
        self.jsonl = jsonl
        self.talker = talker
        self.gsa_talker = gsa_talker
        self.counters: Counter[str] = Counter()
        self._time_known = False

    def fix(
        self,
        fix: Fix,
        since_start_s: float | None = None,
        sky: Callable[[Fix], tuple[SatView, ...]] | None = None,
    ) -> Fix:
        """Publish one solver's result for one epoch (FIX record and NMEA).

        The latency path goes first: GGA to the NMEA TCP and serial outputs as soon as it is
        built, then the ZeroMQ FIX, then JSONL and the other sentences. NMEA files and
        stdout get the epoch's sentences as one block after its JSONL line. ``sky``, when
        given, computes the satellites in view (for GSV) once GGA is out; the fix is
        returned with them."""
        self.counters[f"published_{fix.mode}"] += 1
        if fix.ok:
            self._time_known = True
        nmea = any(o is not None for o in (self.nmea_tcp, self.nmea_serial, self.nmea_lines))
        if nmea:
            tow = fix.gpst_tow_s - (fix.clock_bias_m or 0.0) / C_M_S
            utc = utc_from_gpst(fix.gpst_week, tow)
            gga = gga_sentence(fix, utc=utc, talker=self.talker, gsa_talker=self.gsa_talker)
            self._nmea_live(gga)
        rec = fix_record(fix, since_start_s)
        if self.zmq is not None:
            self.zmq.send("FIX", rec)
        if self.jsonl is not None:
            self.jsonl.write(dumps(rec) + "\n")
        if sky is not None and fix.ok and not fix.sky:
            fix = replace(fix, sky=sky(fix))
        if nmea:
            rest = b"".join(
                sentences_after_gga(
                    fix,
                    utc=utc,
                    talker=self.talker,
                    time_known=self._time_known,
                    gsa_talker=self.gsa_talker,
                )
            )
            self._nmea_live(rest)
            if self.nmea_lines is not None:
                self.nmea_lines.write((gga + rest).decode("ascii"))
        return fix

    def _nmea_live(self, data: bytes) -> None:
        if self.nmea_tcp is not None:
            self.nmea_tcp.publish(data)
        if self.nmea_serial is not None:
            self.nmea_serial.write(data)

    def sky(self, gpst_week: int, gpst_tow_s: float, sats: Sequence[SatView]) -> None:
        """Publish the satellites in view (ZeroMQ ``SKY``)."""
        if self.zmq is not None:
            self.zmq.send("SKY", sky_record(gpst_week, gpst_tow_s, sats))

    def epoch(self, result: Any) -> None:
        """A :class:`service.engine.pipeline.EpochResult`: its fix, then its sky when it has one."""
        fix = self.fix(result.fix, result.since_start_s, getattr(result, "sky", None))
        if fix.sky:
            self.sky(fix.gpst_week, fix.gpst_tow_s, fix.sky)

    def track(self, event: Any) -> None:
        """A :class:`service.engine.tracker.TrackEvent` as a ``TRACK`` record (ZeroMQ and JSONL)."""
        rec = track_record_of(event)
        if self.zmq is not None:
            self.zmq.send("TRACK", rec)
        if self.jsonl is not None:
            self.jsonl.write(dumps(rec) + "\n")

    def all_counters(self, counters: Mapping[str, int | float] | None = None) -> Counter[str]:
        """``counters`` merged with those of the fan-out and of every output."""
        merged: Counter[str] = Counter()
        merged.update(dict(counters or {}))
        merged.update(self.counters)
        for part in (self.nmea_tcp, self.zmq, self.nmea_serial, self.nmea_lines, self.jsonl):
            if part is not None:
                merged.update(dict(part.counters))
        if self.nmea_tcp is not None:
            merged["nmea_clients"] = self.nmea_tcp.n_clients
        return merged

    def status(self, counters: Mapping[str, int | float], **extra: Any) -> None:
        """Publish a ``STATUS`` record of all counters (ZeroMQ)."""
        if self.zmq is not None:
            self.zmq.send("STATUS", status_record(self.all_counters(counters), **extra))

    def gone(self) -> bool:
        """True when every output is a pipe whose reader has left (``replay | head``):
        nothing published from now on can reach anyone. Listeners are never gone."""
        parts = [self.nmea_tcp, self.zmq, self.nmea_serial, self.nmea_lines, self.jsonl]
        used = [p for p in parts if p is not None]
        return bool(used) and all(isinstance(p, LineSink) and p.reader_gone for p in used)

    def reopen(self) -> None:
        """Reopen file outputs (SIGHUP after log rotation)."""
        for sink in (self.nmea_lines, self.jsonl):
            if sink is not None:
                sink.reopen()

    def close(self) -> None:
        for part in (self.nmea_tcp, self.zmq, self.nmea_serial, self.nmea_lines, self.jsonl):
            if part is not None:
                part.close()
