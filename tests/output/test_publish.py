"""Sinks and the fan-out with real peers: TCP clients on 127.0.0.1 (one never reads and is dropped),
ZeroMQ SUB sockets, a pseudo-terminal for the serial sink, logrotate for the line sink, and
gpsd reading our NMEA. Waits are bounded loops; nothing asserts on timing."""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import os
import re
import select
import socket
import threading
import time
from collections.abc import Callable
from types import SimpleNamespace

import pytest
import zmq

from service.core.errors import BindError, ConfigError, InputError
from service.engine.tracker import TrackEvent
from service.output.nmea import sentences_for_fix
from service.output.publish import Publishers
from service.output.records import fix_record, status_record
from service.output.sinks import SINKS, OutputSpec, SinkOptions, open_sinks
from service.output.sinks.base import Sink
from service.output.sinks.lines import JsonlSink, LineSink, NmeaFileSink
from service.output.sinks.nmea_serial import SerialSink
from service.output.sinks.nmea_tcp import NmeaTcpServer
from service.output.sinks.zmq_pub import ZmqPublisher
from tests.support.fixes import SKY, declined_fix, ecef_m, hksc_fix
from tests.support.gpsd import free_port as _free_port
from tests.support.gpsd import gpsd_watching
from tests.support.nmea import C_M_S, hand_parse, horiz_err_m, sec_of_day, utc_of_gpst
from tests.support.schema import validate

HANG_S = 60.0  # waits end here only for a hung run; nothing is timed


def wait_until(pred: Callable[[], bool], what: str, timeout_s: float = HANG_S) -> None:
    """Poll ``pred`` until true; fail (rather than hang) after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.002)


def nmea_epoch(k: int, **changes: object) -> bytes:
    """One epoch of NMEA for a fix at HKSC, 0.1 s after epoch k-1."""
    fix = hksc_fix(gpst_tow_s=444954.0 + 0.1 * k, **changes)
    utc = utc_of_gpst(fix.gpst_week, fix.gpst_tow_s - fix.clock_bias_m / C_M_S)
    return b"".join(sentences_for_fix(fix, utc=utc))


class Reader(threading.Thread):
    """A TCP client that reads everything into ``data`` until EOF."""

    def __init__(self, address: tuple[str, int]) -> None:
        super().__init__(daemon=True)
        self.sock = socket.create_connection(address)
        self.data = bytearray()
        self.start()

    def run(self) -> None:
        with contextlib.suppress(OSError):
            while chunk := self.sock.recv(65536):
                self.data += chunk


# ---- NMEA TCP server ---------------------------------------------------------------------


def test_tcp_slow_client_is_dropped_while_healthy_clients_get_everything():
    server = NmeaTcpServer("127.0.0.1", 0, max_buffer_bytes=64 * 1024)
    try:
        healthy = [Reader(server.address) for _ in range(3)]
        slow = socket.socket()
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect(server.address)
        wait_until(lambda: server.n_clients == 4, "four clients")

        epochs = [nmea_epoch(k) for k in range(10)]
        chunk = b"".join(epochs)  # ~7 kB, ten epochs at 10 Hz
        sent = bytearray()
        for _ in range(20_000):  # at most ~140 MB; the drop comes long before
            server.write_nmea(chunk)
            sent += chunk
            n_sent = len(sent)
            wait_until(lambda n=n_sent: all(len(r.data) == n for r in healthy), "healthy clients")
            if server.counters().get("nmea_clients_dropped_slow"):
                break
        assert server.counters()["nmea_clients_dropped_slow"] == 1
        assert server.n_clients == 3
        assert server.counters()["nmea_clients_accepted"] == 4
        for _ in range(5):  # the healthy ones carry on
            server.write_nmea(chunk)
            sent += chunk
        wait_until(lambda: all(len(r.data) == len(sent) for r in healthy), "healthy clients")
        assert all(r.data == sent for r in healthy)

        # the slow client got a clean prefix of the stream, then the connection closed
        got = bytearray()
        slow.settimeout(HANG_S)
        with contextlib.suppress(ConnectionResetError):
            while part := slow.recv(65536):
                got += part
        assert 0 < len(got) < len(sent) and sent.startswith(got)
        slow.close()
    finally:
        server.close()
    for r in healthy:
        r.join(timeout=HANG_S)
        assert not r.is_alive()  # close() ended their connections


def test_tcp_client_that_leaves_is_forgotten_without_counting_a_drop():
    server = NmeaTcpServer("127.0.0.1", 0)
    try:
        r = Reader(server.address)
        wait_until(lambda: server.n_clients == 1, "one client")
        server.write_nmea(b"$GNTXT,hello*00\r\n")
        wait_until(lambda: len(r.data) > 0, "data")
        r.sock.shutdown(socket.SHUT_RDWR)  # the client leaves (FIN) ...
        r.join(timeout=HANG_S)
        r.sock.close()
        wait_until(lambda: server.n_clients == 0, "client gone")
        server.write_nmea(b"$GNTXT,anyone*00\r\n")  # nobody left: nothing to do, no error
        assert server.counters().get("nmea_clients_dropped_slow", 0) == 0
    finally:
        server.close()


def test_tcp_port_in_use_and_released_on_close():
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    port = blocker.getsockname()[1]
    with pytest.raises(BindError) as err:
        NmeaTcpServer("127.0.0.1", port)
    assert str(err.value) == f"NMEA TCP 127.0.0.1:{port}: address already in use"
    blocker.close()

    server = NmeaTcpServer("127.0.0.1", port)
    client = Reader(server.address)
    wait_until(lambda: server.n_clients == 1, "client")
    server.close()
    client.join(timeout=HANG_S)
    assert not client.is_alive()
    again = NmeaTcpServer("127.0.0.1", port)  # the port is free again
    again.close()


def test_non_loopback_listening_is_warned_about(caplog):
    with caplog.at_level(logging.WARNING, logger="service.output"):
        NmeaTcpServer("127.0.0.1", 0).close()
        pub = ZmqPublisher("tcp://127.0.0.1:*")
        pub.close()
        assert not caplog.records
        NmeaTcpServer("0.0.0.0", 0).close()  # noqa: S104
        pub = ZmqPublisher("tcp://0.0.0.0:*")
        pub.close()
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2 and all("not loopback" in m for m in messages)


# ---- ZeroMQ ------------------------------------------------------------------------------


PROBE_S = -1.0  # since_start_s of FIX probes


def sub_socket(endpoint: str, *topics: bytes, rcvhwm: int | None = None) -> zmq.Socket:
    sock = zmq.Context.instance().socket(zmq.SUB)
    if rcvhwm is not None:
        sock.setsockopt(zmq.RCVHWM, rcvhwm)
    for topic in topics or (b"",):
        sock.setsockopt(zmq.SUBSCRIBE, topic)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    return sock


def join(pub: ZmqPublisher, sub: zmq.Socket, topic: str = "STATUS") -> None:
    """Slow joiner: publish probes until the subscriber receives one."""
    probe = fix_record(hksc_fix(), PROBE_S) if topic == "FIX" else status_record({"probe": 1})
    deadline = time.monotonic() + HANG_S
    while time.monotonic() < deadline:
        pub.send(topic, probe)
        if sub.poll(25):
            return
    raise AssertionError("the SUB socket never received a probe")


def receive(sub: zmq.Socket, n: int) -> list[tuple[str, dict]]:
    """The next n non-probe messages as (topic, record)."""
    out = []
    while len(out) < n:
        assert sub.poll(int(HANG_S * 1000)), f"got {len(out)} of {n} messages"
        frames = sub.recv_multipart()
        assert len(frames) == 2, frames
        topic, rec = frames[0].decode("ascii"), json.loads(frames[1])
        if rec.get("counters", {}).get("probe") or rec.get("since_start_s") == PROBE_S:
            continue
        out.append((topic, rec))
    return out


def test_zmq_topics_are_classes_and_bodies_validate():
    pub = ZmqPublisher("tcp://127.0.0.1:*")
    out = Publishers([pub])
    sub = sub_socket(pub.endpoint)
    fix_only = sub_socket(pub.endpoint, b"FIX")
    try:
        join(pub, sub)
        join(pub, fix_only, "FIX")
        out.track(TrackEvent("C06", "sow", 2161, 444950.2, 0.2, "D1", sow_s=444936.0))
        out.track(TrackEvent("C06", "full", 2161, 444950.3, 0.3, "D1"))
        out.fix(declined_fix(), since_start_s=1.0)
        out.epoch(SimpleNamespace(fix=hksc_fix(), since_start_s=4.0))
        out.status({"frames_ubx": 12}, uptime_s=4.5)
        got = receive(sub, 6)
        assert [t for t, _ in got] == ["TRACK", "TRACK", "FIX", "FIX", "SKY", "STATUS"]
        for topic, rec in got:
            assert rec["class"] == topic and validate(rec) == [], (topic, rec)
        assert got[2][1]["mode"] == "none" and got[3][1]["since_start_s"] == 4.0
        assert [s["prn"] for s in got[4][1]["satellites"]] == [s.prn for s in SKY]
        status = got[5][1]
        assert status["uptime_s"] == 4.5
        counters = status["counters"]
        assert counters["frames_ubx"] == 12
        assert counters["published_none"] == counters["published_fast"] == 1
        assert counters["zmq_TRACK"] == 2 and counters["zmq_FIX"] >= 2 and counters["zmq_SKY"] == 1

        # topic filtering: a FIX subscriber sees FIX only
        out.track(TrackEvent("C09", "full", 2161, 444951.0, 1.0, "D1"))
        out.fix(hksc_fix(gpst_tow_s=444999.0), since_start_s=99.0)
        while True:
            topic, rec = receive(fix_only, 1)[0]
            assert topic == "FIX"
            if rec.get("since_start_s") == 99.0:
                break
    finally:
        sub.close()
        fix_only.close()
        out.close()


def test_zmq_send_never_waits_for_a_subscriber_that_does_not_read():
    pub = ZmqPublisher("inproc://bdsfix-test-hwm", sndhwm=10)
    sub = sub_socket("inproc://bdsfix-test-hwm", rcvhwm=10)
    try:
        join(pub, sub)
        n = 2000
        for seq in range(n):
            assert pub.send("STATUS", status_record({"seq": seq}))
        seqs = []
        while sub.poll(200):
            rec = json.loads(sub.recv_multipart()[1])
            if "seq" in rec["counters"]:
                seqs.append(rec["counters"]["seq"])
        # the queue held only what the high-water marks allow; the rest was dropped by PUB
        assert 0 < len(seqs) < n / 10
        assert seqs == sorted(seqs) and seqs[0] == 0
        assert pub.counters()["zmq_STATUS"] >= n
    finally:
        sub.close()
        pub.close()


def test_zmq_endpoint_in_use_is_a_bind_error():
    first = ZmqPublisher("tcp://127.0.0.1:*")
    try:
        with pytest.raises(BindError, match=re.escape("ZeroMQ tcp://127.0.0.1:")):
            ZmqPublisher(first.endpoint)
    finally:
        first.close()


# ---- line sink ---------------------------------------------------------------------------


def test_line_sink_is_line_buffered_and_reopens_after_logrotate(tmp_path):
    path = tmp_path / "fixes.jsonl"
    path.write_text("old run\n")
    sink = LineSink(str(path))  # truncates by default (replay)
    sink.write("a\n")
    assert path.read_text() == "a\n"  # visible at once: tail -f works
    sink.write("b\n")
    rotated = tmp_path / "fixes.jsonl.1"
    os.rename(path, rotated)  # logrotate renames ...
    sink.write("c\n")  # ... the old descriptor still writes the rotated file ...
    sink.reopen()  # ... until SIGHUP reopens the path
    sink.write("d\n")
    sink.close()
    assert rotated.read_text() == "a\nb\nc\n"
    assert path.read_text() == "d\n"

    appending = LineSink(str(path), append=True)  # the daemon appends
    appending.write("e\n")
    appending.close()
    assert path.read_text() == "d\ne\n"


def test_line_sink_stdout(capsys):
    sink = LineSink("-")
    sink.write("$GNGGA,one*00\r\n")
    sink.reopen()
    sink.write("two\n")
    sink.close()
    assert capsys.readouterr().out == "$GNGGA,one*00\r\ntwo\n"


def test_line_sink_counts_write_errors_instead_of_raising(caplog):
    sink = LineSink("/dev/full", append=True)
    with caplog.at_level(logging.WARNING, logger="service.output"):
        for _ in range(3):
            sink.write("x\n")
    sink.close()
    assert sink.counters()["line_write_errors"] == 3
    assert len(caplog.records) == 1  # logged once, counted every time


def test_line_sink_bad_path_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot write"):
        LineSink(str(tmp_path / "no-such-dir" / "out.nmea"))


# ---- serial sink (pseudo-terminal) -------------------------------------------------------


def read_available(fd: int, until: Callable[[bytes], bool], what: str) -> bytes:
    got = b""
    deadline = time.monotonic() + HANG_S
    while not until(got):
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            got += os.read(fd, 65536)
    return got


def test_serial_sink_writes_nmea_to_a_pty():
    master, slave = os.openpty()
    sink = SerialSink(os.ttyname(slave), 9600)
    try:
        payload = b"".join(nmea_epoch(k) for k in range(20))
        for k in range(20):
            sink.write_nmea(nmea_epoch(k))
        got = read_available(master, lambda b: len(b) >= len(payload), "serial bytes")
        assert got == payload
    finally:
        sink.close()
        os.close(master)
        os.close(slave)


def test_serial_sink_drops_whole_payloads_when_the_port_stalls():
    master, slave = os.openpty()
    sink = SerialSink(os.ttyname(slave), 115200, max_pending_bytes=4096)
    try:
        accepted = []
        for k in range(100_000):  # nobody reads the pty: its buffer fills, then the queue
            before = sink.counters().get("nmea_serial_dropped", 0)
            data = nmea_epoch(k)
            sink.write_nmea(data)
            if sink.counters().get("nmea_serial_dropped", 0) == before:
                accepted.append(data)
            elif before >= 20:
                break
        assert sink.counters()["nmea_serial_dropped"] > 20
        want = b"".join(accepted)
        got = read_available(master, lambda b: len(b) >= len(want), "the accepted payloads")
        assert got == want  # complete sentences only, in order, nothing torn
        for line in got.split(b"\r\n")[:-1]:
            hand_parse(line + b"\r\n")
        # the writer thread takes a payload off its queue after port.write() returns, which
        # may be just after the reader above saw the payload's last byte
        wait_until(lambda: sink.pending_bytes == 0, "an empty queue once all was read")
    finally:
        sink.close()
        os.close(master)
        os.close(slave)


def test_serial_sink_counts_a_vanished_device_and_keeps_going():
    master, slave = os.openpty()
    sink = SerialSink(os.ttyname(slave), 115200)
    os.close(master)  # the device goes away (EIO on the slave)
    try:
        for k in range(50):
            sink.write_nmea(nmea_epoch(k))
            if sink.counters().get("nmea_serial_errors"):
                break
            time.sleep(0.01)
        wait_until(lambda: sink.counters().get("nmea_serial_errors") == 1, "the write error")
        sink.write_nmea(nmea_epoch(99))  # never raises
        assert sink.counters()["nmea_serial_dropped"] >= 1
    finally:
        sink.close()
        os.close(slave)


def test_serial_sink_bad_device_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="NMEA serial"):
        SerialSink(str(tmp_path / "ttyNONE"), 9600)


# ---- the fan-out -------------------------------------------------------------------------


def test_fan_out_sends_the_same_epochs_everywhere(tmp_path):
    jsonl, nmea = tmp_path / "fixes.jsonl", tmp_path / "out.nmea"
    master, slave = os.openpty()
    tcp, zpub = NmeaTcpServer("127.0.0.1", 0), ZmqPublisher("tcp://127.0.0.1:*")
    serial_sink = SerialSink(os.ttyname(slave), 115200)
    out = Publishers([tcp, NmeaFileSink(str(nmea)), serial_sink, zpub, JsonlSink(str(jsonl))])
    client = Reader(tcp.address)
    sub = sub_socket(zpub.endpoint)
    try:
        wait_until(lambda: tcp.n_clients == 1, "TCP client")
        join(zpub, sub)
        fast = hksc_fix(clock_bias_m=-87_654.321)
        out.track(TrackEvent("C06", "sow", 2161, 444950.0, 0.0, "D1", sow_s=444936.0))
        out.fix(declined_fix(gpst_tow_s=444953.0), since_start_s=3.0)
        out.fix(fast, since_start_s=4.0)
        out.sky(fast.gpst_week, fast.gpst_tow_s, fast.sky)
        out.fix(declined_fix(gpst_tow_s=444955.0), since_start_s=5.0)
        out.status({"frames_ubx": 7})

        lines = [json.loads(x) for x in jsonl.read_text().splitlines()]
        assert [r["class"] for r in lines] == ["TRACK", "FIX", "FIX", "FIX"]
        assert all(validate(r) == [] for r in lines)
        text = nmea.read_bytes()
        wait_until(lambda: len(client.data) >= len(text), "TCP NMEA")
        assert bytes(client.data) == text
        assert read_available(master, lambda b: len(b) >= len(text), "serial NMEA") == text

        addresses = [hand_parse(s + b"\r\n")[0] for s in text.split(b"\r\n")[:-1]]
        # declined before any fix: no ZDA; the fix: the full set; declined later: no ZDA
        assert addresses[:2] == ["GNRMC", "GNGGA"] and addresses[-2:] == ["GNRMC", "GNGGA"]
        assert addresses[2:-2] == [
            "GNRMC",
            "GNGGA",
            "GBGSA",
            "GBGSV",
            "GBGSV",
            "GBGSV",
            "GNGST",
            "GNZDA",
        ]
        # NMEA time is the fix's own time: time tag minus the solved clock bias
        gga = hand_parse(text.split(b"\r\n")[3] + b"\r\n")[1]
        utc = utc_of_gpst(fast.gpst_week, fast.gpst_tow_s - fast.clock_bias_m / C_M_S)
        want = (utc - utc.replace(hour=0, minute=0, second=0, microsecond=0)).total_seconds()
        assert abs(sec_of_day(gga[0]) - want) <= 0.005 + 1e-9

        got = receive(sub, 6)
        assert [t for t, _ in got] == ["TRACK", "FIX", "FIX", "SKY", "FIX", "STATUS"]
        counters = got[-1][1]["counters"]
        assert counters["nmea_clients"] == 1 and counters["nmea_clients_accepted"] == 1
        assert counters["published_none"] == 2 and counters["frames_ubx"] == 7
        assert out.all_counters()["published_fast"] == 1
    finally:
        sub.close()
        out.close()
        os.close(master)
        os.close(slave)
    client.join(timeout=HANG_S)
    assert not client.is_alive()


# ---- gpsd as a consumer ------------------------------------------------------------------


@pytest.mark.needs("gpsd")
@pytest.mark.parametrize("gsa_talker", [None, "GN"])
def test_gpsd_reads_a_southern_western_fix_at_10_hz(gsa_talker):
    """gpsd (an independent NMEA parser) connected to our TCP server reports our fixes:
    mode 3, position within 1 cm, time within 0.01 s; with the default GSA (BeiDou's
    talker, GBGSA) its SKY also marks exactly our used satellites and counts them in
    ``uSat`` (issue 23: with GNGSA, gpsd 3.22 showed uSat 0). Epochs are sent once gpsd is
    our client, so none is lost to its start-up; up to 600 epochs (60 s of data) for 10
    timed TPV reports."""
    lat0, lon0, alt0 = -22.951916789, -43.210487654, 702.456  # Rio de Janeiro
    server = NmeaTcpServer("127.0.0.1", 0)
    out = Publishers([server], gsa_talker=gsa_talker)
    fixes = {}
    tpv: list[dict] = []
    sky: list[dict] = []
    try:
        with gpsd_watching(f"tcp://127.0.0.1:{server.address[1]}") as gpsd:
            wait_until(lambda: server.n_clients == 1, "gpsd to connect to our NMEA server")
            for k in range(600):
                if len(tpv) >= 10 and sky:
                    break
                fix = hksc_fix(
                    x_ecef_m=ecef_m(lat0, lon0, alt0),
                    gpst_tow_s=444954.0 + 0.1 * k,
                    clock_bias_m=3_000.0,
                )
                utc = utc_of_gpst(fix.gpst_week, fix.gpst_tow_s - fix.clock_bias_m / C_M_S)
                shown = utc + dt.timedelta(microseconds=5_000)  # NMEA rounds to 0.01 s
                fixes[shown.strftime("%H:%M:%S.") + f"{shown.microsecond // 10_000:02d}"] = fix
                out.fix(fix, since_start_s=0.1 * k)
                for msg in gpsd.messages(0.05):
                    if msg.get("class") == "TPV" and msg.get("mode") == 3 and "time" in msg:
                        tpv.append(msg)
                    elif msg.get("class") == "SKY" and msg.get("satellites"):
                        sky.append(msg)
            assert server.n_clients == 1, f"gpsd was dropped: {gpsd.output()}"
    finally:
        out.close()
    assert len(tpv) >= 10 and sky
    for t in tpv:
        fix = fixes[t["time"][11:22]]  # gpsd: "2021-06-11T03:35:36.130Z", ours to 0.01 s
        assert horiz_err_m(t["lat"], t["lon"], fix.lat_deg, fix.lon_deg) < 0.01, t
        assert abs(t["altHAE"] - fix.alt_m) < 0.01
    assert t["lat"] < 0 and t["lon"] < 0
    used_by_gpsd = {(s["gnssid"], s["svid"]) for s in sky[-1]["satellites"] if s["used"]}
    ours = {int(p[1:]) for p in hksc_fix().used}
    bds_used = {svid for gnssid, svid in used_by_gpsd if gnssid == 3}
    if gsa_talker is None:
        # gpsd 3.22 files IDs 33-64 of the second and later GSV under SBAS (C37, C38 here:
        # see service/output/nmea.py); newer gpsd under BeiDou
        assert bds_used == {p for p in ours if p <= 32} or bds_used == ours
        assert sky[-1]["uSat"] == len(used_by_gpsd) >= len({p for p in ours if p <= 32})
    else:
        # gpsd 3.22 reads a GNGSA's IDs as GPS PRNs: it marks none of the BeiDou ones used
        # (newer gpsd reads the GSA's system ID, 4: BeiDou)
        assert not bds_used or bds_used == ours


# ---- the registry and the order of the fan-out -------------------------------------------


class Recorder(Sink):
    """A sink that logs every call into a list shared with other recorders."""

    def __init__(self, name: str, log: list, nmea: str = "", records: frozenset = frozenset()):
        self.name, self.log = name, log
        self.nmea, self.records = nmea, records  # type: ignore[misc]
        self.closed = False

    def write_nmea(self, data: bytes) -> None:
        self.log.append((self.name, data[3:6].decode(), data.count(b"\r\n")))

    def write_record(self, cls: str, record) -> None:
        self.log.append((self.name, cls))

    def close(self) -> None:
        self.closed = True


def test_fan_out_order_puts_rmc_and_gga_first_and_file_blocks_last():
    calls: list = []
    every = frozenset({"FIX", "SKY", "TRACK", "STATUS"})
    sinks = [
        Recorder("tcp", calls, nmea="live"),
        Recorder("file", calls, nmea="epoch"),
        Recorder("serial", calls, nmea="live"),
        Recorder("zmq", calls, records=every),
        Recorder("jsonl", calls, records=frozenset({"FIX", "TRACK"})),
    ]
    out = Publishers(sinks)
    out.epoch(SimpleNamespace(fix=hksc_fix(), since_start_s=4.0))
    n_rest = calls[4][2]
    assert calls == [
        ("tcp", "RMC", 2),
        ("serial", "RMC", 2),
        ("zmq", "FIX"),
        ("jsonl", "FIX"),
        ("tcp", "GSA", n_rest),
        ("serial", "GSA", n_rest),
        ("file", "RMC", n_rest + 2),
        ("zmq", "SKY"),
    ]
    calls.clear()
    out.track(TrackEvent("C06", "full", 2161, 444950.3, 0.3, "D1"))
    out.status({"x": 1})
    assert calls == [("zmq", "TRACK"), ("jsonl", "TRACK"), ("zmq", "STATUS")]
    out.close()
    assert all(s.closed for s in sinks)


def test_track_records_wait_for_the_next_gga_and_keep_their_place_before_its_fix():
    """TRACK records are held (the JSON and ZeroMQ work of an epoch's subframes is not
    between its last byte and its GGA) and sent, in their order, once the next fix's lead
    sentences are out: each record sink still sees them before that FIX; a STATUS, a
    release (the loop caught up) or the close sends them too."""
    calls: list = []
    every = frozenset({"FIX", "SKY", "TRACK", "STATUS"})
    sinks = [
        Recorder("tcp", calls, nmea="live"),
        Recorder("zmq", calls, records=every),
        Recorder("jsonl", calls, records=frozenset({"FIX", "TRACK"})),
    ]
    out = Publishers(sinks)
    out.track(TrackEvent("C06", "sow", 2161, 444950.2, 0.2, "D1", sow_s=444936.0))
    out.track(TrackEvent("C06", "full", 2161, 444950.3, 0.3, "D1"))
    assert calls == []
    out.epoch(SimpleNamespace(fix=hksc_fix(), since_start_s=4.0))
    assert calls[:7] == [
        ("tcp", "RMC", 2),
        ("zmq", "TRACK"),
        ("jsonl", "TRACK"),
        ("zmq", "TRACK"),
        ("jsonl", "TRACK"),
        ("zmq", "FIX"),
        ("jsonl", "FIX"),
    ]
    for send in (out.release_tracks, lambda: out.status({"x": 1}), out.close):
        calls.clear()
        out.track(TrackEvent("C09", "full", 2161, 444951.0, 1.0, "D1"))
        send()
        assert calls[:2] == [("zmq", "TRACK"), ("jsonl", "TRACK")], send


def test_every_registered_kind_resolves_to_a_factory():
    for kind, target in SINKS.items():
        module, name = target.split(":")
        assert callable(getattr(__import__(module, fromlist=[name]), name)), kind


def test_output_specs_and_open_errors(tmp_path):
    assert OutputSpec.parse("nmea-tcp:127.0.0.1:0") == OutputSpec("nmea-tcp", "127.0.0.1:0")
    for bad, why in [("jsonl", "KIND:SPEC"), ("jsonl:", "KIND:SPEC"), ("carrier-pigeon:x", "kind")]:
        with pytest.raises(ConfigError, match=why):
            OutputSpec.parse(bad)
    with pytest.raises(ConfigError, match="unknown output kind 'carrier-pigeon'"):
        open_sinks([OutputSpec("carrier-pigeon", "x")])
    with pytest.raises(ConfigError, match="HOST:PORT"):
        open_sinks([OutputSpec("nmea-tcp", "nope")])
    # the first outputs are open when the third fails: they are closed, its error raised
    port = _free_port()
    specs = [
        OutputSpec("nmea-tcp", f"127.0.0.1:{port}"),
        OutputSpec("jsonl", str(tmp_path / "fixes.jsonl")),
        OutputSpec("nmea-file", str(tmp_path / "no-such-dir" / "out.nmea")),
    ]
    with pytest.raises(InputError, match=r"out\.nmea"):
        open_sinks(specs)
    # the port is free again: the failed start closed the listener
    sinks = open_sinks(specs[:2], SinkOptions(append=True))
    assert [type(s) for s in sinks] == [NmeaTcpServer, JsonlSink]
    for s in sinks:
        s.close()
