"""Serial faults on real pseudo-terminals, with the real daemon (``bdsfix run``) reading
through pyserial: the device node disappears and comes back (socat ``pty,link=``, many
times: resumption and file-descriptor count), the writer vanishes in the middle of a UBX
frame, and the line speed changes.

Issue 5's "fixes resume within 2 s of the device returning" is tested in two halves, neither
of them timed on the wall clock of a loaded machine: the transport reopens a returning
device within its backoff cap (tests/drivers/test_drivers.py, with a fake clock), and here,
once the daemon has reopened the device (its "reconnected after" log line), the first epoch
the device sends gives a fix (``RESUME_EPOCHS``). Fixes are read from the daemon's JSONL,
and every wait is for an event (a log line, a fix, an empty input queue), bounded only
against a hung run (``HANG_S``).

What a pty can and cannot emulate: a pty carries bytes whatever its termios speed, so a
speed change on a live port is a real tcsetattr on the line the daemon holds open, but the
garbage a real UART produces when the two ends disagree on the rate cannot happen; it is
emulated with a burst of random bytes, after which the data must decode again. What a pty
does show is that the daemon re-applies its configured speed whenever it reopens the device.
"""

from __future__ import annotations

import fcntl
import json
import os
import random
import re
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path
from typing import Any

import pytest

BDSFIX = str(Path(sys.executable).parent / "bdsfix")
EPOCH_S = 0.1  # the simulated receiver's 10 Hz, written in real time after every return
RESUME_EPOCHS = 1  # the first epoch sent after the daemon reopened the device gives a fix
HANG_S = 60.0  # waits for an event end only a hung run


@pytest.fixture(scope="module")
def epochs() -> list[tuple[float, bytes]]:
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config
    from service.sim.simulator import Simulator

    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=60.0))
    return [(ep.tag_gpst_tow_s, data) for ep, data in sim.ubx_epochs()]


class Daemon:
    """``bdsfix run`` on ``source`` with a warm store, fixes in its JSONL and stderr collected
    by a thread."""

    def __init__(self, tmp_path: Path, source: str, *extra: str) -> None:
        from service.core.ephemeris import EphemerisStore
        from service.sim.keplerian import table1_ephemerides

        self.state = tmp_path / "state"
        store = EphemerisStore()
        store.add_all(table1_ephemerides(0.0))
        store.save(self.state / "ephemeris.json")
        self.jsonl = tmp_path / "fixes.jsonl"
        self.err: list[str] = []
        argv = [BDSFIX, "run", "--source", source, "--state-dir", str(self.state)]
        argv += ["--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(self.jsonl)]
        argv += ["--log-level", "info", *extra]
        self.proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        self._reader = threading.Thread(target=self._read_err, daemon=True)
        self._reader.start()

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line.rstrip("\n"))

    def fixes(self) -> list[dict[str, Any]]:
        """The FIX records written so far (whole lines only)."""
        if not self.jsonl.exists():
            return []
        text = self.jsonl.read_text()
        lines = text.splitlines()[: text.count("\n")]
        return [r for r in map(json.loads, lines) if r["class"] == "FIX"]

    def fix_at_or_after(self, tow_s: float) -> dict[str, Any] | None:
        """The first real fix of data at or after ``tow_s``."""
        for rec in self.fixes():
            if rec["mode"] != "none" and rec["gpst_tow_s"] >= tow_s - 1e-6:
                return rec
        return None

    def wait_running(self) -> None:
        """Until the daemon has opened its source (flushing its input) and starts reading."""
        _wait(lambda: self.logged("bdsfix running"), HANG_S, "the daemon to start")

    def wait_reopened(self, n_before: int) -> None:
        """Until the daemon has reopened the device once more than ``n_before`` times."""
        _wait(lambda: self.count("reconnected after") > n_before, HANG_S, "the reopen")

    def count(self, text: str) -> int:
        return sum(text in line for line in list(self.err))

    def fds(self) -> list[str]:
        """What the daemon's descriptors point at, but the store, open only while saved."""
        fd_dir = Path(f"/proc/{self.proc.pid}/fd")
        out = []
        for p in fd_dir.iterdir():
            try:
                target = os.readlink(p)
            except OSError:  # closed while listing
                continue
            if not target.startswith(str(self.state)):
                out.append(target)
        return sorted(out)

    def holds(self, device: str) -> bool:
        return device in self.fds()

    def logged(self, text: str, start: int = 0) -> bool:
        return any(text in line for line in self.err[start:])

    def stop(self) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout=HANG_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self._reader.join(timeout=HANG_S)
        return rc, "\n".join(self.err)

    def counters(self) -> dict[str, int]:
        for line in reversed(self.err):
            if "final counters: " in line:
                text = line.split("final counters: ", 1)[1]
                return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)\b", text)}
        raise AssertionError("no counters line:\n" + "\n".join(self.err[-20:]))


def _wait(pred: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"hung: no {what} within {timeout_s:.0f} s"
        time.sleep(0.01)


def _resume_after_reopen(daemon: Daemon, epochs: Any, write: Any) -> int:
    """Write epochs (at the receiver's rate) from the device's return until a fix of one of
    them is out; the index, among the epochs written, of the first epoch with a fix."""
    written: list[float] = []
    for tow, data in epochs:
        write(data)
        written.append(tow)
        time.sleep(EPOCH_S)
        if daemon.fix_at_or_after(written[0]) is not None or len(written) > 5 * RESUME_EPOCHS:
            break
    _wait(lambda: daemon.fix_at_or_after(written[0]) is not None, HANG_S, "a fix after return")
    fix = daemon.fix_at_or_after(written[0])
    assert fix is not None
    later = [k for k, tow in enumerate(written) if tow <= fix["gpst_tow_s"] + 1e-6]
    return later[-1] if later else len(written)


class SocatPty:
    """A pty made by socat at ``link``; stopping socat removes the link and closes the pty."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            ["socat", "-u", "STDIN", f"pty,link={self.link},raw,echo=0"],
            stdin=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        _wait(self.link.exists, HANG_S, "socat's link")

    def write(self, data: bytes) -> None:
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(data)
        self.proc.stdin.flush()

    def stop(self) -> None:
        if self.proc is None:
            return
        assert self.proc.stdin is not None
        self.proc.terminate()
        self.proc.wait(HANG_S)
        self.proc.stdin.close()
        self.proc = None
        _wait(lambda: not self.link.is_symlink(), HANG_S, "the link to go")


@pytest.mark.slow
@pytest.mark.needs("socat")
def test_device_node_vanishes_and_returns_many_times(tmp_path, epochs):
    """socat's pty node goes away and comes back 12 times (outages of 0.2-0.6 s, and two
    of 1.7 s and 3.2 s that take the backoff to its cap): each time the daemon logs the
    disconnect, backs off and reopens, and the first epoch sent after the reopen gives a
    fix; its descriptor count after all the cycles equals the count before."""
    rng = random.Random(11)
    outages_s = [rng.uniform(0.2, 0.6) for _ in range(10)] + [1.7, 3.2]
    rng.shuffle(outages_s)
    cycles = len(outages_s)
    link = tmp_path / "ttyBDS"
    pty = SocatPty(link)
    pty.start()
    daemon = Daemon(tmp_path, str(link))
    it = iter(epochs)
    resume: list[int] = []
    try:
        daemon.wait_running()
        first_tow = None
        for tow, data in it:  # warm up: until fixes flow
            first_tow = first_tow or tow
            pty.write(data)
            time.sleep(EPOCH_S)
            if daemon.fix_at_or_after(first_tow) is not None:
                break
        fds_before = daemon.fds()
        for outage_s in outages_s:
            n_back = daemon.count("reconnected after")
            pty.stop()
            time.sleep(outage_s)  # the node is gone; the daemon retries with backoff
            pty.start()
            daemon.wait_reopened(n_back)
            resume.append(_resume_after_reopen(daemon, it, pty.write))
        fds_after = daemon.fds()
    finally:
        rc, err = daemon.stop()
        pty.stop()
    print(
        f"first fix after each reopen: epoch {resume} of those sent after it; "
        f"daemon fds {len(fds_before)} before, {len(fds_after)} after"
    )
    assert rc == 0, err[-3000:]
    assert "Traceback" not in err
    assert max(resume) < RESUME_EPOCHS, resume
    assert len(fds_after) == len(fds_before), (fds_before, fds_after)
    assert sum("disconnected" in line for line in daemon.err) == cycles
    assert sum("reconnected after" in line for line in daemon.err) == cycles
    # backoff: only the first failed open of each outage is a warning
    assert sum("cannot open" in line for line in daemon.err) <= cycles
    c = daemon.counters()
    assert c["source_disconnects"] == cycles and c["source_reconnects"] == cycles


class OsPty:
    """An os.openpty pair behind a symlink (the test holds the master)."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = self.slave = -1

    def plug(self) -> str:
        self.master, self.slave = os.openpty()
        tmp = self.link.with_name(self.link.name + ".new")
        tmp.symlink_to(os.ttyname(self.slave))
        tmp.replace(self.link)
        return os.ttyname(self.slave)

    def unread(self) -> int:
        """Bytes written to the device that nobody has read yet (its input queue)."""
        return int(struct.unpack("i", fcntl.ioctl(self.slave, termios.FIONREAD, b"\0" * 4))[0])

    def unplug(self) -> None:
        self.link.unlink(missing_ok=True)
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1


def test_writer_vanishes_in_the_middle_of_a_frame(tmp_path, epochs):
    """Half a UBX frame, then the writer and the node are gone; when the device returns,
    the first complete epoch written after the daemon reopened it gives a fix."""
    pty = OsPty(tmp_path / "ttyBDS")
    dev = pty.plug()
    daemon = Daemon(tmp_path, str(pty.link))
    try:
        daemon.wait_running()
        for _tow, data in epochs[:30]:
            os.write(pty.master, data)
            time.sleep(EPOCH_S / 2)
        _wait(lambda: daemon.fix_at_or_after(epochs[20][0]) is not None, HANG_S, "fixes")
        cut = epochs[30][1]
        os.write(pty.master, cut[: len(cut) // 2 + 7])  # mid-frame (RAWX or MEASX)
        _wait(lambda: pty.unread() == 0, HANG_S, "the daemon to read the half frame")
        n_back = daemon.count("reconnected after")
        pty.unplug()
        time.sleep(0.6)  # the outage
        dev = pty.plug()
        # logged once open (pyserial has flushed the input queue): what follows is read
        daemon.wait_reopened(n_back)
        assert daemon.holds(dev)
        tow_first = epochs[31][0]
        resume = _resume_after_reopen(
            daemon, iter(epochs[31:45]), lambda data: os.write(pty.master, data)
        )
    finally:
        rc, err = daemon.stop()
        pty.unplug()
    assert rc == 0 and "Traceback" not in err, err[-3000:]
    assert resume < RESUME_EPOCHS, resume
    first = [r for r in daemon.fixes() if abs(r["gpst_tow_s"] - tow_first) < 1e-6]
    assert any(r["mode"] != "none" for r in first), first  # nothing lost after the cut
    c = daemon.counters()
    assert c["source_disconnects"] == 1 and c["source_reconnects"] == 1
    assert any("disconnected" in line for line in daemon.err)


def _speed(fd: int) -> tuple[int, int]:
    attrs = termios.tcgetattr(fd)
    return attrs[4], attrs[5]  # ispeed, ospeed


def test_line_speed_changes(tmp_path, epochs):
    """The speed of the live line changes under the daemon (tcsetattr on the pty, as a
    receiver reconfiguration or a stray ``stty`` does), with a burst of garbage standing for
    the bytes mis-sampled meanwhile: no disconnect, fixes continue. After the device
    returns the daemon has set its configured speed (115200) again."""
    pty = OsPty(tmp_path / "ttyBDS")
    dev = pty.plug()
    daemon = Daemon(tmp_path, f"serial:{pty.link}:115200")
    rng = random.Random(3)
    try:
        daemon.wait_running()
        assert daemon.holds(dev)
        assert _speed(pty.master) == (termios.B115200, termios.B115200)
        for _tow, data in epochs[:20]:
            os.write(pty.master, data)
            time.sleep(EPOCH_S / 2)
        attrs = termios.tcgetattr(pty.master)
        attrs[4] = attrs[5] = termios.B9600
        termios.tcsetattr(pty.master, termios.TCSANOW, attrs)
        assert _speed(pty.slave) == (termios.B9600, termios.B9600)  # one line, both ends
        os.write(pty.master, rng.randbytes(600))
        tow_after = epochs[20][0]
        for _tow, data in epochs[20:40]:
            os.write(pty.master, data)
            time.sleep(EPOCH_S / 2)
        _wait(lambda: daemon.fix_at_or_after(tow_after) is not None, HANG_S, "fixes after garbage")
        after = [r for r in daemon.fixes() if abs(r["gpst_tow_s"] - tow_after) < 1e-6]
        assert any(r["mode"] != "none" for r in after), after  # the next valid frame decodes
        n_back = daemon.count("reconnected after")
        pty.unplug()  # the device returns with the kernel's default speed ...
        dev = pty.plug()
        assert _speed(pty.master) != (termios.B115200, termios.B115200)
        daemon.wait_reopened(n_back)
        assert daemon.holds(dev)
        assert _speed(pty.master) == (termios.B115200, termios.B115200)  # ... and gets ours
        tow_back = epochs[41][0]
        for _tow, data in epochs[41:55]:
            os.write(pty.master, data)
            time.sleep(EPOCH_S / 2)
        _wait(lambda: daemon.fix_at_or_after(tow_back) is not None, HANG_S, "fixes after return")
    finally:
        rc, err = daemon.stop()
        pty.unplug()
    assert rc == 0 and "Traceback" not in err, err[-3000:]
    c = daemon.counters()
    assert c["source_disconnects"] == 1  # the unplug, not the speed change
    assert c.get("source_bytes_skipped", 0) > 0  # the garbage was counted and skipped
