"""The status page's server (``--output http:HOST:PORT``) on a real loopback socket: its
security headers, 404 for every path that is not its own with nothing read from disk,
read-only methods, the Host check, the client cap, the JSON of the latest records, and a
client that stops reading dropped while the epoch loop runs on."""

from __future__ import annotations

import socket
import sys
import threading
import time

import pytest

from service.commands.run import decode_chunks
from service.daemon.loop import Runner
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from service.output.records import SCHEMAS
from service.output.sinks import OutputSpec, SinkOptions, open_sinks
from service.output.sinks.http_page import MAX_HEAD_BYTES, HttpPageServer, load_page
from service.output.sinks.lines import JsonlSink
from service.sim.scenario import builtin_scenario
from tests.support.http import SseReader, get, request

SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
    "x-frame-options": "DENY",
    "cache-control": "no-store",
    "cross-origin-resource-policy": "same-origin",
}


@pytest.fixture
def server():
    srv = HttpPageServer("127.0.0.1", 0)
    yield srv
    srv.close()


def wait_until(pred, what: str, bound_s: float = 60.0) -> None:
    """Poll ``pred`` with a generous overall bound (a hang guard, not a timing)."""
    end = time.monotonic() + bound_s
    while not pred():
        if time.monotonic() > end:
            raise AssertionError(f"never happened: {what}")
        time.sleep(0.01)


def assert_secured(answer) -> None:
    for name, value in SECURITY_HEADERS.items():
        assert answer.headers.get(name) == value, name
    csp = answer.headers["content-security-policy"]
    for part in ("default-src 'none'", "connect-src 'self'", "frame-ancestors 'none'"):
        assert part in csp
    assert "unsafe-inline" not in csp and "http" not in csp  # nothing from elsewhere


def test_the_page_is_the_packaged_asset_with_its_headers(server):
    page = get(server.address, "/")
    assert page.status == 200
    assert page.body == load_page()
    assert page.headers["content-type"] == "text/html; charset=utf-8"
    assert_secured(page)
    # self-contained: no URL of another origin anywhere in it
    text = page.body.decode()
    assert "http://" not in text.replace("http://www.w3.org/2000/svg", "")
    assert "https://" not in text and "src=" not in text and "@import" not in text
    head = get(server.address, "/", method="HEAD")
    assert head.status == 200 and head.body == b""
    assert head.headers["content-length"] == str(len(load_page()))


class DiskReads:
    """Audit events of file access raised by the server's thread (PEP 578)."""

    EVENTS = ("open", "os.listdir", "os.scandir", "os.chdir", "shutil.copyfile")

    def __init__(self) -> None:
        self.seen: list[tuple[str, tuple]] = []
        self.on = False
        sys.addaudithook(self._hook)  # cannot be removed: switched off after the test

    def _hook(self, event: str, args: tuple) -> None:
        if self.on and event in self.EVENTS and threading.current_thread().name == "bdsfix-http":
            self.seen.append((event, args))


ODD_TARGETS = [
    "/../",
    "/..",
    "/../../../../etc/passwd",
    "/etc/passwd",
    "//etc/passwd",
    "/%2e%2e/%2e%2e/etc/passwd",
    "/..%2f..%2fetc%2fpasswd",
    "/status_page.html",
    "/service/output/sinks/status_page.html",
    "/index.html",
    "/?file=/etc/passwd",
    "/fix.json/../../etc/passwd",
    "/events/..",
    "/%00",
    "/\\..\\..\\etc\\passwd",
    "/" + "a" * 6000,
    "/" + "../" * 2000,
    "*",
    "http://127.0.0.1/etc/passwd",
]


def test_paths_outside_the_page_get_404_and_nothing_is_read_from_disk(server):
    reads = DiskReads()
    reads.on = True
    try:
        for target in ODD_TARGETS:
            answer = get(server.address, target)
            assert answer.status == 404, target
            assert answer.body == b"not found\n"
            assert_secured(answer)
        # a request head longer than the server reads: 404 too
        huge = b"GET /" + b"x" * (4 * MAX_HEAD_BYTES) + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
        answer = request(server.address, huge)
        assert answer.status == 404
        assert_secured(answer)
        for target in ("/", "/events"):  # the page's own answers do not read it either
            if target == "/events":
                reader = SseReader(server.address)
                assert reader.wait_for(lambda ev: any(n == "state" for n, _ in ev))
                reader.close()
            else:
                assert get(server.address, target).status == 200
    finally:
        reads.on = False
    assert reads.seen == []
    assert server.counters()["http_not_found"] >= len(ODD_TARGETS)


def test_read_only_methods_odd_requests_and_foreign_hosts(server):
    for method in ("POST", "PUT", "DELETE", "OPTIONS", "TRACE", "PATCH"):
        answer = get(server.address, "/", method=method)
        assert answer.status == 405, method
        assert answer.headers["allow"] == "GET, HEAD"
        assert_secured(answer)
    bad = request(server.address, b"GET /\r\n\r\n")  # HTTP/0.9 style: no version
    assert bad.status == 400
    assert_secured(bad)
    # a page whose own host name resolves to 127.0.0.1 (DNS rebinding) is not answered
    for host in ("evil.example", "evil.example:8080", "127.0.0.1.evil.example", "10.0.0.1"):
        answer = get(server.address, "/fix.json", host=host)
        assert answer.status == 421, host
        assert_secured(answer)
    for host in ("localhost", "localhost:8080", "127.0.0.1", "[::1]:8080"):
        assert get(server.address, "/", host=host).status == 200, host


def test_json_of_the_latest_records(server):
    answer = get(server.address, "/fix.json")
    assert answer.status == 503 and answer.headers["retry-after"] == "1"
    assert_secured(answer)
    fix = {"class": "FIX", "solver": "fast", "mode": "none", "gpst_week": 1, "gpst_tow_s": 2.0}
    fix |= {"n_full": 0, "n_frac": 4, "reason": "r", "reason_code": "too_few_full"}
    server.write_record("FIX", fix)
    server.write_record("STATUS", {"class": "STATUS", "counters": {"epochs": 1}})
    wait_until(lambda: get(server.address, "/status.json").status == 200, "a STATUS served")
    import json

    got = get(server.address, "/fix.json")
    assert got.headers["content-type"] == "application/json"
    assert json.loads(got.body) == fix
    assert json.loads(get(server.address, "/status.json").body)["counters"] == {"epochs": 1}
    assert SCHEMAS  # the records as published: the page adds nothing to /fix.json


def test_connections_over_the_cap_are_closed_at_once():
    srv = HttpPageServer("127.0.0.1", 0, max_clients=2)
    try:
        readers = [SseReader(srv.address) for _ in range(2)]
        wait_until(lambda: srv.n_event_streams == 2, "two event streams")
        with socket.create_connection(srv.address) as third:
            assert third.recv(100) == b""  # closed at once (it sent nothing: an orderly close)
        assert srv.counters()["http_clients_refused"] == 1
        readers[0].close()
        wait_until(lambda: srv.n_event_streams == 1, "one stream left")
        assert get(srv.address, "/").status == 200  # a slot is free again
        readers[1].close()
    finally:
        srv.close()


def test_loopback_only_unless_asked_with_the_zeromq_warning(caplog):
    srv = open_sinks([OutputSpec.parse("http:127.0.0.1:0")], SinkOptions())[0]
    srv.close()
    assert not [r for r in caplog.records if "not loopback" in r.getMessage()]
    srv = HttpPageServer("0.0.0.0", 0)  # noqa: S104  (bound and closed: the warning only)
    srv.close()
    said = [r.getMessage() for r in caplog.records]
    assert [m for m in said if "listens on 0.0.0.0" in m and "not loopback" in m]


def test_a_client_that_stops_reading_is_dropped_while_the_loop_runs_on(tmp_path):
    """The built-in scenario's 600 epochs through the real loop (Runner) into the status page
    and a JSONL file, while one event-stream client never reads (a small receive buffer) and
    another reads everything: the loop handles every epoch, the stalled client is dropped
    (``http_clients_dropped_slow``) and the reader gets every FIX the JSONL file has."""
    srv = HttpPageServer("127.0.0.1", 0, backlog_bytes=128 * 1024)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect(srv.address)
    stalled.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    reader = SseReader(srv.address)
    wait_until(lambda: srv.n_event_streams == 2, "both event streams open")
    chunks, week, store, iono, _offset, _info = builtin_scenario()
    jsonl = tmp_path / "fixes.jsonl"
    outputs = Publishers([srv, JsonlSink(str(jsonl))])
    runner = Runner(
        decode_chunks(chunks, week), Pipeline(store, iono), outputs, status_interval_s=1e9
    )
    n = runner.run()
    assert n == 600
    import json

    fixes = [r for r in map(json.loads, jsonl.read_text().splitlines()) if r["class"] == "FIX"]
    assert len(fixes) == 600
    assert reader.wait_for(lambda ev: sum(name == "fix" for name, _ in ev) == 600)
    got = [data for name, data in reader.events if name == "fix"]
    assert got == fixes
    assert srv.counters()["http_clients_dropped_slow"] == 1
    assert srv.n_event_streams == 1  # the reader's
    outputs.close()
    reader.close()
    stalled.close()


def test_the_daemon_config_opens_it_with_its_cap(tmp_path):
    """``output = ["http:..."]`` and ``http_max_clients`` in bdsfix.toml, as ``run`` reads
    and opens them."""
    from service.commands.run import output_specs
    from service.daemon.config import load_config

    toml = tmp_path / "bdsfix.toml"
    toml.write_text(
        'nmea_tcp = ""\nzmq = ""\noutput = ["http:127.0.0.1:0"]\nhttp_max_clients = 3\n'
    )
    cfg = load_config(toml)
    specs = output_specs(cfg)
    assert specs == [OutputSpec("http", "127.0.0.1:0")]
    (sink,) = open_sinks(specs, SinkOptions(http_max_clients=cfg.http_max_clients))
    try:
        assert isinstance(sink, HttpPageServer) and sink.max_clients == 3
        assert get(sink.address, "/").status == 200
    finally:
        sink.close()


def test_a_port_in_use_is_a_bind_error(server):
    from service.core.errors import BindError

    with pytest.raises(BindError, match="address already in use"):
        HttpPageServer(*server.address)
