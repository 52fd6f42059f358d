"""The virtual receiver as a configurable u-blox receiver on a real pty, for the set-up
tests: in this process (a thread serving the pty's master) or as ``bdsfix simulate --pty
--wait-config`` in a subprocess. Timeouts only stop a hung run (``HANG_S``)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.sim.cfg import CfgResponder
from service.sim.configurable import ConfigurableReceiver
from service.sim.scenario import broadcast_table1, scenario_config
from service.sim.simulator import Simulator
from tests.support.paths import ROOT

HANG_S = 120.0
ACK_WAIT_S = 60.0
"""The set-up's wait for each ACK/NAK in tests that expect an answer: only a hung receiver
reaches it (the no-answer tests set their own)."""
BEIJING_TRUE = (39.9, 116.4, 50.0)
"""Where the virtual receiver is (``bdsfix simulate``'s default place), written out."""


@dataclass
class InProcessReceiver:
    device: str
    responder: CfgResponder
    receiver: ConfigurableReceiver


@contextlib.contextmanager
def receiver_thread(**responder_kw: object) -> Iterator[InProcessReceiver]:
    """A configurable virtual receiver (Table 1, near Beijing, 10 Hz) on a raw pty, served
    by a thread; yields the slave's device path and the receiver's CFG state."""
    master, slave = os.openpty()
    tty.setraw(slave)
    responder = CfgResponder(base_period_ms=100, **responder_kw)  # type: ignore[arg-type]
    ephs = broadcast_table1()

    def make_sim(offset_s: float) -> Simulator:
        return Simulator(ephs, scenario_config(duration_s=600.0, start_offset_s=offset_s))

    rx = ConfigurableReceiver(master, make_sim, responder, base_period_ms=100)
    thread = threading.Thread(target=rx.serve, daemon=True)
    thread.start()
    try:
        yield InProcessReceiver(os.ttyname(slave), responder, rx)
    finally:
        rx.stop()
        thread.join(HANG_S)
        os.close(master)
        os.close(slave)


@dataclass
class SimProcess:
    proc: subprocess.Popen[bytes]
    device: str
    err_path: Path


@contextlib.contextmanager
def simulate_wait_config(tmp_path: Path, *extra: str) -> Iterator[SimProcess]:
    """``bdsfix simulate --pty --wait-config`` (Table 1, near Beijing, 10 Hz, 10 min) in a
    subprocess; yields its pty once it has printed it. Ended with SIGTERM."""
    err_path = tmp_path / f"simulate-{len(list(tmp_path.glob('simulate-*')))}.err"
    argv = [sys.executable, "-m", "service", "simulate", "--pty", "--wait-config"]
    argv += ["--duration-s", "600", "-v", *extra]
    with err_path.open("wb") as err:
        proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err)
    try:
        deadline = time.monotonic() + HANG_S
        while True:
            first = err_path.read_text(errors="replace").split("\n", 1)
            if len(first) == 2 and first[0].startswith("/dev/"):
                break
            assert proc.poll() is None, err_path.read_text(errors="replace")
            assert time.monotonic() < deadline, "simulate printed no pty"
            time.sleep(0.02)
        yield SimProcess(proc, first[0], err_path)
    finally:
        proc.terminate()
        proc.wait(HANG_S)


def read_stream(device: str, n_rawx: int) -> list[tuple[bytes, object]]:
    """Frames read from ``device`` (pyserial, pyubx2 with every protocol) until ``n_rawx``
    RXM-RAWX have come: (raw, parsed) each."""
    import serial
    from pyubx2 import UBXReader

    out: list[tuple[bytes, object]] = []
    deadline = time.monotonic() + HANG_S
    with serial.Serial(device, 115200, timeout=0.2) as link:
        reader = UBXReader(link, quitonerror=0)
        while sum(getattr(m, "identity", "") == "RXM-RAWX" for _, m in out) < n_rawx:
            assert time.monotonic() < deadline, f"hung: {len(out)} frames"
            raw, msg = reader.read()
            if raw is not None:
                out.append((raw, msg))
    return out


def rawx_svs(msg: Any) -> dict[int, bool]:
    """BeiDou svId -> prValid of one RXM-RAWX."""
    n = int(msg.numMeas)
    return {
        int(getattr(msg, f"svId_{i:02d}")): bool(getattr(msg, f"prValid_{i:02d}"))
        for i in range(1, n + 1)
        if int(getattr(msg, f"gnssId_{i:02d}")) == 3
    }


def wait_for(pred: object, what: str) -> None:
    """Until ``pred()``; only a hung run (``HANG_S``) fails here."""
    deadline = time.monotonic() + HANG_S
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        time.sleep(0.01)
