"""The NMEA TCP server under too many connections: over ``max_clients`` a connection is
accepted and closed at once and counted (``nmea_clients_refused``) while the clients it
serves keep their data; when accept fails for want of descriptors (EMFILE, in a child
process with a low RLIMIT_NOFILE) the listener backs off instead of spinning, the failures
are counted (``nmea_accept_errors``) and accepting resumes once descriptors are free."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable

import pytest

from service.commands.cli import build_parser
from service.core.errors import ConfigError
from service.daemon.config import load_config
from service.output.sinks import OutputSpec, SinkOptions, open_sinks
from service.output.sinks.nmea_tcp import ACCEPT_BACKOFF_MIN_S, NmeaTcpServer
from tests.support.paths import ROOT


def _wait(cond: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def _recv_all(sock: socket.socket, n: int, timeout_s: float = 10.0) -> bytes:
    sock.settimeout(timeout_s)
    got = b""
    while len(got) < n:
        chunk = sock.recv(4096)
        if not chunk:
            break
        got += chunk
    return got


def test_connections_over_the_cap_are_closed_at_once_and_counted():
    server = NmeaTcpServer("127.0.0.1", 0, max_clients=2)
    clients = []
    try:
        for n in (1, 2):
            clients.append(socket.create_connection(server.address))
            _wait(lambda n=n: server.n_clients == n)
        refused = [socket.create_connection(server.address) for _ in range(5)]
        clients += refused
        for s in refused:  # closed by the server: end of stream, nothing sent
            assert _recv_all(s, 1) == b""
        c = server.counters()
        assert c["nmea_clients_refused"] == 5
        assert c["nmea_clients"] == 2 and c["nmea_clients_accepted"] == 2
        server.write_nmea(b"$GNGGA,x*00\r\n")
        for s in clients[:2]:
            assert _recv_all(s, 13) == b"$GNGGA,x*00\r\n"
        clients[0].close()  # a slot frees: the next connection is served
        _wait(lambda: server.n_clients == 1)
        clients.append(socket.create_connection(server.address))
        _wait(lambda: server.counters()["nmea_clients_accepted"] == 3)
        assert server.n_clients == 2
    finally:
        for s in clients:
            s.close()
        server.close()


CHILD = textwrap.dedent(
    """
    import json, os, resource, sys, time
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
    from service.output.sinks.nmea_tcp import NmeaTcpServer
    server = NmeaTcpServer("127.0.0.1", 0, max_clients=1000)
    spare = []
    while True:  # take every descriptor left but one: the first client gets it
        try:
            spare.append(os.open(os.devnull, os.O_RDONLY))
        except OSError:
            break
    os.close(spare.pop())
    print(server.address[1], flush=True)
    sys.stdin.readline()  # the parent has flooded
    t0 = time.monotonic()
    while time.monotonic() - t0 < 2.0:
        server.write_nmea(b"$GNGGA,x*00\\r\\n")
        time.sleep(0.1)
    stuck = dict(server.counters())
    for fd in spare:
        os.close(fd)
    time.sleep(1.5)  # at most one backoff (1 s) until the listener is polled again
    print(json.dumps({"stuck": stuck, "after": dict(server.counters())}), flush=True)
    server.close()
    """
)


def test_accept_failing_for_want_of_descriptors_backs_off_and_recovers():
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    socks: list[socket.socket] = []
    try:
        assert child.stdin is not None and child.stdout is not None
        port = int(child.stdout.readline())
        healthy = socket.create_connection(("127.0.0.1", port))
        socks.append(healthy)
        time.sleep(0.3)  # accepted: the child's last descriptor
        for _ in range(40):  # wait in the backlog: accept fails with EMFILE
            socks.append(socket.create_connection(("127.0.0.1", port)))
        child.stdin.write("go\n")
        child.stdin.flush()
        got = _recv_all(healthy, 13 * 10)
        report = json.loads(child.stdout.readline())
        assert child.wait(timeout=30) == 0
    finally:
        for s in socks:
            s.close()
        if child.poll() is None:
            child.kill()
            child.wait()
    stuck, after = report["stuck"], report["after"]
    # the client served before the flood kept its data
    assert got.startswith(b"$GNGGA,x*00\r\n" * 10)
    assert stuck["nmea_clients"] == 1
    # accept failed and was counted, but the loop backed off: over ~2 s a spinning loop
    # would fail thousands of times, one that backs off (from 50 ms, doubling) a handful
    assert 1 <= stuck["nmea_accept_errors"] <= 2.5 / ACCEPT_BACKOFF_MIN_S
    # descriptors free again: the waiting connections are served
    assert after["nmea_clients"] == 41


def test_the_cap_is_a_setting_of_run_and_a_flag_of_replay(tmp_path):
    assert load_config(None).nmea_tcp_max_clients == 64
    toml = tmp_path / "bdsfix.toml"
    toml.write_text('source = "x"\nnmea_tcp_max_clients = 3\n')
    assert load_config(toml).nmea_tcp_max_clients == 3
    for bad in (0, -1, 2.5):
        with pytest.raises(ConfigError, match="nmea_tcp_max_clients"):
            load_config(None, {"nmea_tcp_max_clients": bad})
    parser = build_parser()
    assert parser.parse_args(["replay"]).nmea_tcp_max_clients == 64
    assert parser.parse_args(["replay", "--nmea-tcp-max-clients", "5"]).nmea_tcp_max_clients == 5
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(["replay", "--nmea-tcp-max-clients", "0"])
    assert exit_info.value.code == 2
    (sink,) = open_sinks(
        [OutputSpec("nmea-tcp", "127.0.0.1:0")], SinkOptions(nmea_tcp_max_clients=7)
    )
    try:
        assert isinstance(sink, NmeaTcpServer) and sink.max_clients == 7
    finally:
        sink.close()
