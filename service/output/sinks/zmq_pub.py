"""``zmq``: every record on a ZeroMQ PUB socket (an endpoint such as ``tcp://127.0.0.1:10111``).

Framing: each message is two frames, ``[topic, body]``: the topic is the record's class in
ASCII (``FIX``, ``SKY``, ``TRACK``, ``STATUS``), so a SUB socket filters with
``setsockopt(SUBSCRIBE, b"FIX")``; the body is the record as compact UTF-8 JSON (see
:mod:`service.output.records`). Sends use ``NOBLOCK``; a send the socket refuses (EAGAIN) is
dropped and counted (``zmq_dropped``). libzmq's PUB itself drops, silently and per
subscriber, messages for a subscriber whose queue has reached the high-water mark
(``sndhwm``); the sender never sees those drops, so they are not in the counters. Binding a
TCP address other than loopback logs a warning.

Closing flushes: the publisher has a ZeroMQ context of its own and terminates it in
:meth:`ZmqPublisher.close`, which waits (up to ``linger_ms``) until what was sent, such as
the STATUS at shutdown, has been handed to the subscribers' connections. A socket closed in
a shared context that the process never terminates (pyzmq does not at exit) loses
whatever its I/O thread had not written yet when the process ends. ``inproc://`` endpoints
use the shared ``zmq.Context.instance()``, since an in-process peer must share the context.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils import z85

from service.core.counters import Counters
from service.core.errors import BindError, ConfigError
from service.core.ratelog import RateLimitedLog
from service.output.records import dumps
from service.output.sinks.base import RECORD_CLASSES, Sink, SinkOptions, is_loopback

log = logging.getLogger(__name__)

_BIND_ERRNOS = (errno.EADDRINUSE, errno.EADDRNOTAVAIL, errno.EACCES)


def open_sink(spec: str, options: SinkOptions) -> ZmqPublisher:
    return ZmqPublisher(
        spec,
        curve_secret_key_file=options.zmq_curve_secret_key,
        curve_clients_dir=options.zmq_curve_clients,
    )


CURVE_KEY_Z85_CHARS = 40
"""A CURVE public key in Z85 (32 bytes, ZeroMQ RFC 26 and RFC 32)."""


def client_keys(clients_dir: str) -> dict[bytes, bool]:
    """The public keys of the client certificates (``*.key``) in ``clients_dir``, each
    checked: ConfigError naming the first file pyzmq cannot read or whose key is no CURVE
    key (pyzmq's loader would fail on it and allow no client at all)."""
    if not Path(clients_dir).is_dir():
        raise ConfigError(f"ZeroMQ CURVE clients {clients_dir}: not a directory")
    keys: dict[bytes, bool] = {}
    for path in sorted(Path(clients_dir).glob("*.key")):  # as zmq.auth.load_certificates
        why = ""
        try:
            public, _ = zmq.auth.load_certificate(path)
        except (OSError, ValueError, IndexError) as exc:
            why = str(exc) or type(exc).__name__
        else:
            if len(public) != CURVE_KEY_Z85_CHARS or not _is_z85(public):
                why = f"public-key is not a {CURVE_KEY_Z85_CHARS}-character Z85 CURVE key"
        if why:
            raise ConfigError(
                f"ZeroMQ CURVE client certificate {path}: {why[:200]} (a bad file in "
                "zmq_curve_clients would lock every client out: fix or remove it)"
            )
        keys[public] = True
    return keys


def _is_z85(text: bytes) -> bool:
    try:
        z85.decode(text)
    except (ValueError, KeyError):
        return False
    return True


class ZmqPublisher(Sink):
    """ZeroMQ PUB socket sending ``[topic, JSON]`` messages without ever waiting.

    CURVE (optional): ``curve_secret_key_file`` is the server's secret certificate
    (``zmq.auth.create_certificates`` format); subscribers must then know the server's
    public key. ``curve_clients_dir`` holds the public certificates of the subscribers
    allowed in (``*.key``, the czmq convention pyzmq follows); without it any client that
    knows the server key may connect. Clients refused by the handshake or the ZAP
    authenticator receive nothing.

    Fail closed: a clients directory without a server secret key is a ConfigError (it would
    publish in the clear), and so is a certificate in it that pyzmq cannot read or whose
    public key is not a Z85 CURVE key (pyzmq would drop the whole directory, and with it
    every client); the number of clients allowed is logged (INFO; a WARNING for none).
    """

    records = frozenset(RECORD_CLASSES)

    def __init__(
        self,
        endpoint: str = "tcp://127.0.0.1:10111",
        sndhwm: int = 1000,
        linger_ms: int = 1000,
        curve_secret_key_file: str = "",
        curve_clients_dir: str = "",
    ) -> None:
        if curve_clients_dir and not curve_secret_key_file:
            raise ConfigError(
                f"ZeroMQ CURVE clients {curve_clients_dir} without a server secret key "
                "(zmq_curve_secret_key): that would publish in the clear; give both"
            )
        self._counters = Counters()
        self._log = RateLimitedLog(log)  # a failing send fails every record
        host = endpoint.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]")
        if endpoint.startswith("tcp://") and not is_loopback(host):
            log.warning("ZeroMQ PUB binds %s, not loopback", endpoint)
        self._auth: Any = None
        # A context of our own, terminated in close() so that the last records are flushed
        # before the process exits (with CURVE, its ZAP authenticator serves this socket
        # only); inproc peers must share the process's context.
        self._own_ctx = bool(curve_secret_key_file) or not endpoint.startswith("inproc://")
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
            error = BindError if exc.errno in _BIND_ERRNOS else ConfigError
            raise error(f"ZeroMQ {endpoint}: {exc}") from exc
        except ConfigError:
            self.close(linger_ms=0)
            raise
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)

    def _setup_curve(self, secret_file: str, clients_dir: str) -> None:
        try:
            public, secret = zmq.auth.load_certificate(secret_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"ZeroMQ CURVE secret key {secret_file}: {exc}") from exc
        if not secret:
            raise ConfigError(f"ZeroMQ CURVE secret key {secret_file}: no secret-key in file")
        clients = client_keys(clients_dir) if clients_dir else {}
        self._auth = ThreadAuthenticator(self._ctx, log=log)
        self._auth.start()
        if clients_dir:
            self._auth.configure_curve(domain="*", location=clients_dir)
            if clients:
                log.info("ZeroMQ CURVE: %d clients allowed (%s)", len(clients), clients_dir)
            else:
                log.warning("ZeroMQ CURVE: no client certificate (*.key) in %s", clients_dir)
        else:
            self._auth.configure_curve(domain="*", location=zmq.auth.CURVE_ALLOW_ANY)
            log.info("ZeroMQ CURVE: any client that knows the server key")
        self._sock.curve_secretkey = secret
        self._sock.curve_publickey = public
        self._sock.curve_server = True

    def send(self, topic: str, record: Mapping[str, Any]) -> bool:
        """Send ``[topic, JSON]``; False (and counted) when the socket refuses it."""
        try:
            self._sock.send_multipart(
                [topic.encode("ascii"), dumps(record).encode("utf-8")], flags=zmq.NOBLOCK
            )
        except zmq.Again:
            self._counters["zmq_dropped"] += 1
            return False
        except zmq.ZMQError as exc:
            self._counters["zmq_errors"] += 1
            self._log.warning(type(exc).__name__, "ZeroMQ send failed: %s", exc)
            return False
        self._counters[f"zmq_{topic}"] += 1
        return True

    def write_record(self, cls: str, record: Mapping[str, Any]) -> None:
        self.send(cls, record)

    def counters(self) -> Mapping[str, int]:
        return dict(self._counters)

    def close(self, linger_ms: int | None = None) -> None:
        """Close the socket; with our own context, wait (up to the linger time) until the
        records already sent have been written to the subscribers' connections."""
        self._sock.close(linger=self._linger_ms if linger_ms is None else linger_ms)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._own_ctx:
            self._ctx.term()
            self._own_ctx = False
