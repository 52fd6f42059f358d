"""The NTRIP source: URL parsing, chunked transfer coding, and the transport against real
casters on loopback (pygnssutils' caster in NTRIP v1 and v2 mode; a small socket server of
our own for what that caster does not do: chunked coding, a 503, a v1 answer with the data
right after its status line)."""

from __future__ import annotations

import base64
import logging
import queue
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.ntrip import ChunkDecoder, NtripRefusedError, open_ntrip
from service.core.errors import ConfigError
from service.core.ntripurl import PASSWORD_ENV, NtripUrl, parse_ntrip_url, redact
from service.core.types import Ephemeris, MeasurementEpoch
from tests.support.ntrip_caster import MOUNT, PASSWORD, USER, Caster, rtcm_frames
from tests.support.paths import DATA

HIROSHIMA = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
HANG_S = 60.0


# --- the URL ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "host", "port", "mount", "user", "password"),
    [
        ("ntrip://alice:pw-1@127.0.0.1:2101/MOUNT", "127.0.0.1", 2101, "MOUNT", "alice", "pw-1"),
        ("ntrip://caster.example/RTCM3EPH", "caster.example", 2101, "RTCM3EPH", "", ""),
        ("NTRIP://alice:pw-1@[::1]:2102/M_1.x-y", "::1", 2102, "M_1.x-y", "alice", "pw-1"),
        ("ntrip://me%40mail.example:pw%3Aq@h:80/M", "h", 80, "M", "me@mail.example", "pw:q"),
        ("ntrip://alice:pa/ss@word@h/M", "h", 2101, "M", "alice", "pa/ss@word"),  # unencoded
        ("ntrip://alice@h:2101/M", "h", 2101, "M", "alice", "from-env"),
    ],
)
def test_ntrip_urls_parse(text, host, port, mount, user, password):
    url = parse_ntrip_url(text, env={PASSWORD_ENV: "from-env"})
    assert (url.host, url.port, url.mount, url.user, url.password) == (
        host,
        port,
        mount,
        user,
        password,
    )
    shown = f"{url} {url!r} {url.redacted()}"
    assert (user and user not in shown) or not user
    assert (password and password not in shown) or not password


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("ntrip://u:hunter2@h:2101", "no mountpoint"),
        ("ntrip://u:hunter2@h:2101/", "no mountpoint"),
        ("ntrip://u:hunter2@h:99999/M", "not in 1-65535"),
        ("ntrip://u:hunter2@h:/M", "not in 1-65535"),
        ("ntrip://u:hunter2@h:x/M", "not in 1-65535"),
        ("ntrip://:hunter2@h/M", "empty user"),
        ("ntrip://u:hunter2@/M", "no host"),
        ("ntrip://u:hunter2@h h/M", "not HOST[:PORT]"),
        ("ntrip://u:hunter2@h/M?gga=1", "no query"),
        ("ntrip://u:hunter2@h/M/N", "not a mountpoint name"),
        ("http://u:hunter2@h/M", "not an NTRIP URL"),
    ],
)
def test_malformed_ntrip_urls_say_why_without_the_credentials(text, why):
    with pytest.raises(ConfigError) as err:
        parse_ntrip_url(text)
    msg = str(err.value)
    assert why in msg and "expected ntrip://user:pass@host:port/MOUNT" in msg
    assert "hunter2" not in msg and "u:" not in msg.split("expected")[0]


def test_redact_hides_everything_before_the_last_at():
    assert redact("ntrip://u:p@ss@h:1/M") == "ntrip://***@h:1/M"
    assert redact("ntrip://h:1/M") == "ntrip://h:1/M"


@given(
    st.sampled_from(["ntrip://", "NTRIP://", "ntrips://", "http://", "https://", "ntrip:", ""]),
    st.text(min_size=0, max_size=20),
    st.text(min_size=0, max_size=20),
    st.sampled_from(["h", "caster.example:2101", "[::1]:2102"]),
)
def test_redact_hides_any_credentials_whatever_the_scheme(scheme, user, password, hostport):
    """Issue 23: any scheme (not only exactly ntrip://), and a user or password holding
    ``@ : /`` or a newline: nothing of them is left, the host and mountpoint are."""
    user, password = "USR" + user, "PWD" + password
    text = f"{scheme}{user}:{password}@{hostport}/MOUNT"
    shown = redact(text)
    assert shown.endswith(f"***@{hostport}/MOUNT")
    assert "USR" not in shown and "PWD" not in shown
    assert shown.startswith(scheme if scheme.endswith("//") else "***@")


@pytest.mark.parametrize(
    "text",
    [
        "ntrips://alice:hunter2@h/M",
        "http://alice:hunter2@h:2101/M",
        "ntrip:alice:hunter2@h/M",
        "alice:hunter2@h/M",
        "ntrip://alice:hun\nter2@h:99999/M",
        "ntrip://alice:hun\nter2@h h/M",
    ],
)
def test_urls_of_other_schemes_are_refused_without_the_credentials(text):
    """Issue 23: these printed the password (as a file name that cannot be read, or, with a
    newline, the line after it); now a URL-like nav entry is refused as a URL, redacted."""
    with pytest.raises(ConfigError) as err:
        parse_ntrip_url(text)
    msg = str(err.value)
    assert "hunter2" not in msg and "alice" not in msg and "hun" not in msg
    assert "\n" not in msg


def test_authorization_is_rfc7617_basic():
    url = NtripUrl("h", 2101, "M", user="Aladdin", password="open sesame")  # noqa: S106
    assert url.authorization() == "Basic QWxhZGRpbjpvcGVuIHNlc2FtZQ=="  # RFC 7617 section 2
    assert NtripUrl("h", 2101, "M").authorization() is None


# --- chunked transfer coding (RFC 9112 section 7.1) ---------------------------------------


def _chunked(body: bytes, sizes: list[int]) -> bytes:
    """``body`` in chunks of ``sizes`` (cycled), with an extension now and then, then the
    last chunk and an empty trailer: written from RFC 9112 section 7.1, not from the code."""
    out = b""
    pos = 0
    i = 0
    while pos < len(body):
        n = max(1, sizes[i % len(sizes)])
        piece = body[pos : pos + n]
        ext = b";name=value" if i % 3 == 1 else b""
        out += f"{len(piece):X}".encode() + ext + b"\r\n" + piece + b"\r\n"
        pos += n
        i += 1
    return out + b"0\r\n\r\n"


@given(
    st.binary(max_size=3000),
    st.lists(st.integers(1, 700), min_size=1, max_size=8),
    st.lists(st.integers(1, 97), min_size=1, max_size=40),
)
def test_chunk_decoder_any_split(body, sizes, splits):
    coded = _chunked(body, sizes)
    dec = ChunkDecoder()
    out = b""
    pos = 0
    i = 0
    while pos < len(coded):
        n = splits[i % len(splits)]
        out += dec.feed(coded[pos : pos + n])
        pos += n
        i += 1
    assert out == body
    assert dec.done


def test_chunk_decoder_refuses_a_bad_size_line():
    with pytest.raises(ValueError, match="bad chunk size"):
        ChunkDecoder().feed(b"zz\r\nabc\r\n")
    with pytest.raises(ValueError, match="no CRLF"):
        ChunkDecoder().feed(b"3\r\nabcXY")


@pytest.mark.parametrize("size", [b"-5", b"-0", b"+5", b"0x5", b"5_0", b" -1", b""])
def test_chunk_decoder_refuses_a_size_that_is_not_hex_digits(size):
    """Issue 23: a negative size was taken (int(x, 16) reads a sign, a 0x prefix and
    underscores) and the framing passed on as data; RFC 9112 7.1: chunk-size = 1*HEXDIG."""
    dec = ChunkDecoder()
    with pytest.raises(ValueError, match="bad chunk size"):
        dec.feed(size + b"\r\n" + b"\xd3\x00\x13" * 4 + b"\r\n0\r\n\r\n")


# --- against pygnssutils' caster --------------------------------------------------------


def _independent_1042(path) -> set[tuple[str, float]]:
    """(PRN, t_oe) of every RTCM 1042 in a file, read with pyrtcm alone (DF488, DF493)."""
    from pyrtcm import RTCMReader

    out = set()
    with open(path, "rb") as fh:
        for _raw, msg in RTCMReader(fh):
            if msg.identity == "1042":
                out.add((f"C{msg.DF488:02d}", float(msg.DF493)))
    return out


def _collect(src, until, what: str) -> list:
    """Events of ``src`` (in a thread) until ``until(events)``; only a hang fails."""
    events: list = []
    q: queue.Queue = queue.Queue()

    def read() -> None:
        try:
            for ev in src:
                q.put(ev)
        except Exception as exc:
            q.put(exc)

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + HANG_S
    while not until(events):
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        try:
            ev = q.get(timeout=0.2)
        except queue.Empty:
            continue
        if isinstance(ev, Exception):
            raise ev
        events.append(ev)
    return events


@pytest.mark.parametrize("version", ["1.0", "2.0"])
def test_transport_reads_every_1042_of_the_hiroshima_stream_from_a_real_caster(
    version, tmp_path, caplog
):
    """pygnssutils' caster serves the whole Hiroshima OEM729 stream (MSM, 1042, 1019, ...)
    in 3 s cycles: the source gives exactly the file's 1042 ephemerides (by PRN and t_oe,
    read independently with pyrtcm), passes the base station's MSM epochs on as they are
    (the daemon drops them), and at DEBUG level logs no credential."""
    caplog.set_level(logging.DEBUG)
    want = _independent_1042(HIROSHIMA)
    assert len(want) >= 7
    with Caster(HIROSHIMA, cycle_s=3.0, version=version) as caster:
        src = open_ntrip(parse_ntrip_url(caster.url()))
        try:
            events = _collect(
                src,
                lambda evs: {(e.prn, e.toe_sow_s) for e in evs if isinstance(e, Ephemeris)} >= want,
                "every 1042 of the file",
            )
        finally:
            src.close()
    got = {(e.prn, e.toe_sow_s) for e in events if isinstance(e, Ephemeris)}
    assert got == want
    assert all(e.source == "rtcm" for e in events if isinstance(e, Ephemeris))
    assert any(isinstance(e, MeasurementEpoch) for e in events)
    assert src.counters["connects"] == 1
    text = "\n".join(r.getMessage() for r in caplog.records)
    token = base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()
    for secret in (USER, PASSWORD, token):
        assert secret not in text


def test_refused_credentials_and_unknown_mountpoint_end_the_source(caplog):
    caplog.set_level(logging.DEBUG)
    with Caster(HIROSHIMA) as caster:
        bad_pw = open_ntrip(parse_ntrip_url(caster.url(password="hunter2")))  # noqa: S106
        with pytest.raises(NtripRefusedError, match=r"refused the credentials \(HTTP 401\)"):
            list(bad_pw)
        no_mount = open_ntrip(parse_ntrip_url(caster.url().replace(MOUNT, "NOSUCH")))
        with pytest.raises(NtripRefusedError, match="no mountpoint 'NOSUCH'"):
            list(no_mount)
    assert bad_pw.counters["refused"] == no_mount.counters["refused"] == 1
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "hunter2" not in text and PASSWORD not in text


# --- against a caster of our own (what pygnssutils' does not do) -------------------------


class _Server:
    """A real TCP server on loopback answering each connection with the next of
    ``answers`` (bytes, then close); records the requests."""

    def __init__(self, answers: list[bytes]) -> None:
        self.answers = list(answers)
        self.requests: list[bytes] = []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        for answer in self.answers:
            conn, _ = self.sock.accept()
            with conn:
                req = b""
                while b"\r\n\r\n" not in req:
                    data = conn.recv(4096)
                    if not data:
                        break
                    req += data
                self.requests.append(req)
                for i in range(0, len(answer), 7):  # in small pieces
                    conn.sendall(answer[i : i + 7])
        self.sock.close()


def _hk_frames() -> bytes:
    return b"".join(f for f in rtcm_frames(HIROSHIMA) if ((f[3] << 4) | (f[4] >> 4)) == 1042)


def _events(port: int, n_eph: int) -> tuple[list, Any]:
    url = parse_ntrip_url(f"ntrip://{USER}:{PASSWORD}@127.0.0.1:{port}/EPH")
    src = open_ntrip(url, reconnect_max_s=0.2)
    try:
        evs = _collect(
            src,
            lambda e: sum(isinstance(x, Ephemeris) for x in e) >= n_eph,
            f"{n_eph} ephemerides",
        )
    finally:
        src.close()
    return evs, src


def test_chunked_v2_503_and_a_bare_v1_answer():
    """First a 503 (retried), then an NTRIP v2 answer in chunked coding that ends with the
    last chunk (the stream's end: reconnect), then a v1 ``ICY 200 OK`` with the data right
    after the status line: every 1042 comes through each time; the request is NTRIP v2
    with RFC 7617 Basic authentication."""
    frames = _hk_frames()
    n_eph = sum(1 for _ in _independent_1042_frames(frames))
    v2 = (
        b"HTTP/1.1 200 OK\r\nNtrip-Version: Ntrip/2.0\r\nContent-Type: gnss/data\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n" + _chunked(frames, [100, 37, 500])
    )
    v1 = b"ICY 200 OK\r\n" + frames
    server = _Server([b"HTTP/1.1 503 Service Unavailable\r\n\r\n", v2, v1])
    evs, src = _events(server.port, 2 * n_eph)
    ephs = [e for e in evs if isinstance(e, Ephemeris)]
    assert {(e.prn, e.toe_sow_s) for e in ephs} == _independent_1042(HIROSHIMA)
    assert ephs[:n_eph] == ephs[n_eph : 2 * n_eph]
    assert src.counters["http_errors"] == 1
    # the 503 is no connection; the end of the chunked stream is a disconnect
    assert src.counters["connects"] == 2 and src.counters["disconnects"] >= 1
    req = server.requests[0].decode()
    assert req.startswith("GET /EPH HTTP/1.1\r\n")
    assert "Ntrip-Version: Ntrip/2.0\r\n" in req
    token = base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()
    assert f"Authorization: Basic {token}\r\n" in req


def _independent_1042_frames(frames: bytes) -> Iterator[bytes]:
    from io import BytesIO

    from pyrtcm import RTCMReader

    for raw, msg in RTCMReader(BytesIO(frames)):
        if msg.identity == "1042":
            yield raw


# --- casters that misbehave (issue 23) ------------------------------------------------------


class _Misbehaving:
    """A real TCP server on loopback: connection ``i`` (from 0) gets ``answer(i)`` after
    the request, ``per_byte_s`` between bytes (0: at once), then is closed; until stop()."""

    def __init__(self, answer, per_byte_s: float = 0.0) -> None:
        self.answer = answer
        self.per_byte_s = per_byte_s
        self.accepted = 0
        self.stopped = threading.Event()
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self.stopped.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            i, self.accepted = self.accepted, self.accepted + 1
            with conn:
                req = b""
                while b"\r\n\r\n" not in req:
                    data = conn.recv(4096)
                    if not data:
                        break
                    req += data
                answer = self.answer(i)
                try:
                    if not self.per_byte_s:
                        conn.sendall(answer)
                    for k in range(len(answer)) if self.per_byte_s else ():
                        if self.stopped.wait(self.per_byte_s):
                            break
                        conn.sendall(answer[k : k + 1])
                except OSError:
                    pass
        self.sock.close()

    def stop(self) -> None:
        self.stopped.set()


def _pump(transport, until, what: str) -> None:
    """Read ``transport`` until ``until()``; only a hang (HANG_S) fails."""
    deadline = time.monotonic() + HANG_S
    while not until():
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        transport.read(4096)


def _frozen(logger_name: str):
    """A rate-limited log whose clock never moves: what it lets through does not depend on
    how long the test takes (the rate limit is tested in tests/core/test_ratelog.py)."""
    from service.core.ratelog import RateLimitedLog

    return RateLimitedLog(logging.getLogger(logger_name), clock=lambda: 0.0)


OK_200 = b"HTTP/1.1 200 OK\r\nNtrip-Version: Ntrip/2.0\r\nContent-Type: gnss/data\r\n\r\n"


@pytest.mark.parametrize(
    "answer",
    [
        OK_200,  # and close
        OK_200.replace(b"\r\n\r\n", b"\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n"),
    ],
    ids=["200-and-close", "bad-chunk-size"],
)
def test_a_caster_that_answers_200_and_closes_gets_no_retry_storm(answer, caplog):
    """Issue 23: the backoff was reset at every answered connection, so such a caster got
    about 4 connections a second, each with two WARNINGs ("reconnected", "disconnected").
    Now: the backoff grows to its maximum and stays there, no "reconnected" is logged nor
    counted, and the drops are one rate-limited WARNING; then a caster that sends a whole
    RTCM 3 frame resets the backoff (one INFO "connected")."""
    caplog.set_level(logging.DEBUG)
    frames = _hk_frames()
    good_from = 8
    server = _Misbehaving(lambda i: answer if i < good_from else OK_200 + frames)
    url = parse_ntrip_url(f"ntrip://{USER}:{PASSWORD}@127.0.0.1:{server.port}/EPH")
    src = open_ntrip(url, reconnect_max_s=0.2)
    t = src.transport
    t.backoff_initial_s = t._backoff_s = 0.01
    t._drop_log = _frozen("drivers.transport")
    try:
        _pump(t, lambda: t.counters["drops_before_data"] >= good_from - 1, "dropped connections")
        assert t._backoff_s == t.backoff_max_s == 0.2  # grown, never reset by an answer
        assert t.counters.get("reconnects", 0) == 0
        warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(warnings) == 1, warnings
        assert "connection lost before any data" in warnings[0]
        assert not any("reconnected" in r.getMessage() for r in caplog.records)
        _pump(t, lambda: t.counters.get("transport_bytes", 0) >= len(frames), "the frames")
        assert t._backoff_s == t.backoff_initial_s  # real data: the backoff is reset
        infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        assert sum(m.endswith(": connected") for m in infos) == 1, infos
    finally:
        src.close()
        server.stop()


def test_a_caster_trickling_its_header_is_dropped_counted_and_logged(caplog):
    """Issue 23, slow loris: a caster sending its header a byte at a time (never ending it)
    held the connection for as long as it liked (16 KiB at 1 B/s: 4.5 h) with no log line
    and no counter. Now the header must be whole within header_timeout_s."""
    caplog.set_level(logging.DEBUG)
    header = b"HTTP/1.1 200 OK\r\nX-Pad: " + b"a" * 16000
    server = _Misbehaving(lambda i: header, per_byte_s=0.02)
    url = parse_ntrip_url(f"ntrip://127.0.0.1:{server.port}/EPH")
    src = open_ntrip(url, reconnect_max_s=0.2, header_timeout_s=0.5)
    t = src.transport
    box: list = []
    reader = threading.Thread(target=lambda: box.append(t.read(4096)), daemon=True)
    try:
        reader.start()
        reader.join(HANG_S)
        assert not reader.is_alive(), f"hung: the header read did not end in {HANG_S:.0f} s"
        assert box == [b""]
        assert t.counters["header_timeouts"] == 1 and t.counters["open_failures"] == 1
        assert t.counters.get("connects", 0) == 0
        lines = [
            r for r in caplog.records if "no whole answer header within 0.5 s" in r.getMessage()
        ]
        assert len(lines) == 1 and lines[0].levelno == logging.WARNING
    finally:
        src.close()
        server.stop()


def test_a_garbage_stream_after_200_is_counted_and_logged_once_at_info(caplog):
    """Issue 23: a caster answering 200 then sending bytes that hold no RTCM 3 frame raised
    nothing at INFO and a DEBUG line per false sync byte (145k lines in 20 s). Now each such
    stream is counted (no_rtcm_streams), the first logged once at INFO, the framer's
    checksum lines are rate-limited, and the backoff is not reset."""
    import random

    caplog.set_level(logging.DEBUG)
    rng = random.Random(23)
    garbage = [bytes(rng.getrandbits(8) for _ in range(70_000)) for _ in range(3)]
    server = _Misbehaving(lambda i: OK_200 + garbage[i % 3])
    url = parse_ntrip_url(f"ntrip://127.0.0.1:{server.port}/EPH")
    src = open_ntrip(url, reconnect_max_s=0.2)
    src.decoder.framer._log = _frozen("drivers.framing")
    t = src.transport
    t.backoff_initial_s = t._backoff_s = 0.01
    try:
        events = []
        deadline = time.monotonic() + HANG_S
        while t.counters.get("no_rtcm_streams", 0) < 3:
            assert time.monotonic() < deadline, "hung: three garbage streams not judged"
            events += src.decoder.feed(t.read(4096))
    finally:
        src.close()
        server.stop()
    assert events == []
    assert src.counters["bad_checksum_rtcm"] + src.counters["bad_length_rtcm"] >= 100
    msgs = [r.getMessage() for r in caplog.records]
    info = [m for m in msgs if "sends no RTCM 3" in m]
    assert len(info) == 1 and "'EPH'" in info[0], info
    assert next(r for r in caplog.records if "sends no RTCM 3" in r.getMessage()).levelno == (
        logging.INFO
    )
    assert sum("checksum failure" in m for m in msgs) <= 2  # one per protocol key
    drops = t.counters["drops_before_data"]
    assert drops >= 2 and t.counters.get("reconnects", 0) == 0
    assert t._backoff_s == min(0.01 * 2**drops, t.backoff_max_s)  # never reset
