"""The loop reads a live receiver in its own thread (service/daemon/loop.py,
``Runner.live_inline``): a real pty through pyserial and a real TCP connection, with the
virtual receiver's UBX through the real driver.

Read inline, the loop must publish exactly what it publishes with its reader thread, with
no reader thread running; survive a TCP server that drops the connection (reconnect, the
epochs after it solved); keep its timers (STATUS, the systemd watchdog) while the receiver
is silent; and take a network nav source's ephemerides from that source's own thread.
Nothing here is timed: each run ends when the loop has seen what it waits for, and a hung
run is stopped by a timer that fails the test.
"""

from __future__ import annotations

import os
import socket
import threading
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.source import BinarySource, open_source
from service.core.ephemeris import EphemerisStore
from service.daemon.loop import Runner
from service.engine.pipeline import EpochResult, Pipeline
from service.output.publish import Publishers
from service.output.sinks.lines import JsonlSink
from service.sim.scenario import broadcast_table1, scenario_config
from service.sim.simulator import Simulator

HANG_S = 120.0  # only a hung run takes this long
READER = "bdsfix-reader"


@pytest.fixture(scope="module")
def receiver() -> tuple[int, list[tuple[float, bytes]]]:
    """GPS week and (time tag, UBX bytes) of 12 s of the virtual receiver at 10 Hz: no
    ephemeris in the stream (they come from the store or a network source)."""
    cfg = scenario_config(duration_s=12.0)
    sim = Simulator(broadcast_table1(), cfg)
    return cfg.start_gpst_week, [(ep.tag_gpst_tow_s, data) for ep, data in sim.ubx_epochs()]


def _warm_store() -> EphemerisStore:
    store = EphemerisStore()
    store.add_all(broadcast_table1())
    return store


class _Pty:
    """A real pty: the test writes the master end, the daemon's pyserial opens the slave."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.device = os.ttyname(self.slave)

    def write_all(self, chunks: list[bytes]) -> threading.Thread:
        """Write ``chunks`` in order from a thread (a pty holds only so much unread)."""

        def run() -> None:
            for data in chunks:
                os.write(self.master, data)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


def _serial_source(device: str, week: int) -> BinarySource:
    src = open_source(device, gps_week=week)
    assert isinstance(src, BinarySource) and src.live
    src.transport.open_now()  # type: ignore[attr-defined]  # opened before any byte is written
    return src


class _Until:
    """Stops the runner once ``n`` epochs are solved, noting the threads that ran meanwhile;
    a timer stops a hung run (and the test fails on ``hung``)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.results: list[EpochResult] = []
        self.threads: set[str] = set()
        self.runner: Runner | None = None
        self.hung = False
        self._timer = threading.Timer(HANG_S, self._hang)

    def _hang(self) -> None:
        self.hung = True
        assert self.runner is not None
        self.runner.request_stop()

    def __enter__(self) -> _Until:
        self._timer.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._timer.cancel()

    def on_result(self, result: EpochResult) -> None:
        self.results.append(result)
        self.threads |= {t.name for t in threading.enumerate()}
        if len(self.results) >= self.n and self.runner is not None:
            self.runner.request_stop()


def _run_pty(tmp_path: Path, receiver: Any, live_inline: bool) -> tuple[bytes, _Until]:
    week, epochs = receiver
    pty = _Pty()
    jsonl = tmp_path / f"inline-{live_inline}.jsonl"
    outputs = Publishers([JsonlSink(str(jsonl))])
    src = _serial_source(pty.device, week)
    try:
        with _Until(len(epochs)) as until:
            until.runner = Runner(
                src,
                Pipeline(_warm_store()),
                outputs,
                source_counters=src.counters,
                status_interval_s=1e9,
                on_result=until.on_result,
                live_inline=live_inline,
            )
            writer = pty.write_all([data for _tow, data in epochs])
            until.runner.run()
            writer.join(HANG_S)
    finally:
        src.close()
        outputs.close()
        pty.close()
    assert not until.hung
    return jsonl.read_bytes(), until


def test_a_pty_read_inline_publishes_what_the_reader_thread_publishes(tmp_path, receiver):
    """Every epoch written to the pty is solved, in order, with no reader thread; the FIX and
    TRACK records are byte for byte those of the loop with its reader thread."""
    _week, epochs = receiver
    inline, run_inline = _run_pty(tmp_path, receiver, live_inline=True)
    threaded, run_threaded = _run_pty(tmp_path, receiver, live_inline=False)
    tows = [tow for tow, _data in epochs]
    assert [r.fix.gpst_tow_s for r in run_inline.results] == pytest.approx(tows, abs=1e-9)
    assert any(r.fix.mode == "fast" for r in run_inline.results)
    assert any(r.fix.mode == "spp" for r in run_inline.results)
    assert READER not in run_inline.threads
    assert READER in run_threaded.threads  # the check above can see a reader thread
    assert inline == threaded


class _Server:
    """A TCP server (a receiver's TCP port) that sends the first part of the epochs, drops
    the connection, takes the daemon's reconnection and sends the rest."""

    def __init__(self, parts: list[list[bytes]]) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.parts = parts
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        for k, part in enumerate(self.parts):
            conn, _ = self.sock.accept()
            conn.sendall(b"".join(part))
            if k + 1 < len(self.parts):
                conn.close()  # the receiver's server goes away: the daemon reconnects
            else:
                self.done.wait(HANG_S)  # the last connection stays up until the test ends
                conn.close()

    def close(self) -> None:
        self.done.set()
        self.thread.join(HANG_S)
        self.sock.close()


def test_a_tcp_source_read_inline_reconnects_and_solves_every_epoch(receiver):
    """The server drops the connection after the first half: the loop (no reader thread)
    logs the disconnect, reconnects and solves every epoch of both halves, in order."""
    week, epochs = receiver
    data = [d for _tow, d in epochs]
    half = len(data) // 2
    server = _Server([data[:half], data[half:]])
    src = open_source(f"tcp:127.0.0.1:{server.port}", gps_week=week)
    assert isinstance(src, BinarySource) and src.live
    try:
        with _Until(len(epochs)) as until:
            until.runner = Runner(
                src,
                Pipeline(_warm_store()),
                Publishers(),
                source_counters=src.counters,
                status_interval_s=1e9,
                on_result=until.on_result,
            )
            until.runner.run()
    finally:
        src.close()
        server.close()
    assert not until.hung
    tows = [tow for tow, _data in epochs]
    assert [r.fix.gpst_tow_s for r in until.results] == pytest.approx(tows, abs=1e-9)
    assert READER not in until.threads
    c = until.runner.counters()
    assert (c["source_connects"], c["source_disconnects"], c["source_reconnects"]) == (2, 1, 1)


def test_timers_run_while_a_live_receiver_is_silent(receiver):
    """Nothing arrives on the pty: the loop, blocked in no read for longer than the
    transport's timeout, keeps sending STATUS and feeding the watchdog; its third watchdog
    call stops it, and the final STATUS follows."""
    week, _epochs = receiver
    pty = _Pty()
    src = _serial_source(pty.device, week)
    statuses: list[dict] = []

    class Statuses(Publishers):
        def status(self, counters, **extra) -> None:
            statuses.append(dict(counters))

    dog: list[int] = []
    runner: Runner | None = None

    def watchdog() -> None:
        dog.append(len(statuses))
        if len(dog) == 3:
            assert runner is not None
            runner.request_stop()

    hung = threading.Event()
    try:
        runner = Runner(
            src,
            Pipeline(_warm_store()),
            Statuses(),
            source_counters=src.counters,
            status_interval_s=1e-3,
            watchdog=watchdog,
            watchdog_interval_s=1e-3,
        )
        timer = threading.Timer(HANG_S, lambda: (hung.set(), runner.request_stop()))
        timer.start()
        n = runner.run()
        timer.cancel()
    finally:
        src.close()
        pty.close()
    assert not hung.is_set()
    assert n == 0 and len(dog) == 3
    assert dog[0] >= 1 and dog[2] > dog[1] > dog[0]  # STATUS went on between watchdog calls
    assert len(statuses) > dog[2]  # the final STATUS
    assert statuses[-1]["source_transport_bytes"] == 0


def test_a_network_nav_thread_feeds_the_inline_loop(receiver):
    """No ephemeris in the store or the receiver's stream; a network nav source (its own
    thread) gives the current sets: the loop reading the pty inline takes them and fast
    fixes follow."""
    week, epochs = receiver
    sets = broadcast_table1()
    nav_done = threading.Event()

    def network() -> Iterator[object]:
        yield from sets
        nav_done.set()

    pty = _Pty()
    src = _serial_source(pty.device, week)
    store = EphemerisStore()
    try:
        with _Until(len(epochs)) as until:
            until.runner = Runner(
                src,
                Pipeline(store),
                Publishers(),
                source_counters=src.counters,
                status_interval_s=1e9,
                on_result=until.on_result,
                nav_sources=[("ntrip://***@h:2101/M", network(), {"connects": 1})],
            )

            def write_after_network() -> None:
                nav_done.wait(HANG_S)  # every network set is queued before the receiver
                pty.write_all([data for _tow, data in epochs]).join(HANG_S)

            writer = threading.Thread(target=write_after_network, daemon=True)
            writer.start()
            until.runner.run()
            writer.join(HANG_S)
    finally:
        src.close()
        pty.close()
    assert not until.hung
    assert READER not in until.threads
    assert any(r.fix.mode == "fast" for r in until.results)
    c = until.runner.counters()
    assert c["ntrip_ephemerides"] == len(sets) == len(store)


@pytest.mark.parametrize(
    ("spec", "live"),
    [
        ("tcp:127.0.0.1:2101", True),
        ("tcp:[::1]:2101", True),
        ("tcp:localhost:2101", True),
        ("tcp:receiver.example.invalid:2101", False),
    ],
)
def test_a_tcp_source_is_read_inline_only_by_address(spec, live):
    """A TCP receiver given by a host name keeps the reader thread: its name is resolved at
    every connect attempt, which a silent resolver holds far longer than the loop may wait
    (nothing is connected here: the sources are only opened)."""
    src = open_source(spec)
    assert isinstance(src, BinarySource)
    assert src.live is live
    src.close()
