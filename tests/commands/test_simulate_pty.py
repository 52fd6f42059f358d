"""``bdsfix simulate --pty`` as a new user runs it (issue 23): the virtual receiver waits
for its reader, repeats its RTCM 1042 ephemerides as a receiver repeats its navigation
data, so ``bdsfix run`` on the pty gets its fast fix within the first second of data (it
came 44 s late), and it ends at ``--duration-s`` after its reader has left (it hung).

Real ptys, pyserial as the reader (it flushes its input on open, as the daemon's does),
real subprocesses. Timeouts only end a hung run (``HANG_S``); every time asserted is data
time."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from tests.support.paths import ROOT

HANG_S = 120.0
BDSFIX = [sys.executable, "-m", "service"]


def _wait(pred, what: str) -> None:
    deadline = time.monotonic() + HANG_S
    while not pred():
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        time.sleep(0.02)


@contextlib.contextmanager
def _simulate(tmp_path: Path, *extra: str) -> Iterator[tuple[subprocess.Popen, Path, Path]]:
    """``bdsfix simulate --pty --link DIR/sim.tty`` in a subprocess, once its link is there."""
    link, err = tmp_path / "sim.tty", tmp_path / "simulate.err"
    with err.open("wb") as fh:
        proc = subprocess.Popen(
            [*BDSFIX, "simulate", "--pty", "--link", str(link), *extra],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=fh,
        )
    try:
        _wait(lambda: link.exists() or proc.poll() is not None, "pty link")
        assert proc.poll() is None, err.read_text()
        yield proc, link, err
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.wait(HANG_S)


def _frames(device: Path, n_rawx: int, *, flush: bool = True) -> list[str]:
    """The identities of the frames read from ``device`` until ``n_rawx`` RXM-RAWX have
    come: UBX names, ``RTCM1042`` for each 1042. The reader is pyserial (which flushes the
    input on open, as the daemon's does), or with ``flush=False`` a plain ``open`` of the
    raw device that loses nothing."""
    import serial
    from pyubx2 import RTCM3_PROTOCOL, UBX_PROTOCOL, UBXReader

    out: list[str] = []
    deadline = time.monotonic() + HANG_S
    opened = (
        serial.Serial(str(device), 115200, timeout=0.2)
        if flush
        else open(device, "rb", buffering=0)  # noqa: SIM115
    )
    with opened as link:
        reader = UBXReader(link, protfilter=UBX_PROTOCOL | RTCM3_PROTOCOL, quitonerror=0)
        while out.count("RXM-RAWX") < n_rawx:
            assert time.monotonic() < deadline, f"hung: {len(out)} frames"
            raw, msg = reader.read()
            if raw is not None:
                out.append("RTCM" + msg.identity if raw[0] == 0xD3 else msg.identity)
    return out


def test_the_stream_starts_with_its_reader_and_repeats_the_1042s(tmp_path):
    """Nothing goes to nobody: a reader that comes late and loses nothing on open reads
    the 12 ephemerides, then the first epoch; the 1042s come again every second of data
    (10 epochs)."""
    with _simulate(tmp_path, "--duration-s", "30") as (proc, link, err):
        time.sleep(1.0)  # a reader that comes late (no deadline: what it misses is checked)
        frames = _frames(link, 25, flush=False)
        proc.terminate()
    rawx_before = [frames[: i + 1].count("RXM-RAWX") for i in range(len(frames))]
    batches = [
        rawx_before[i]
        for i, f in enumerate(frames)
        if f == "RTCM1042" and (i == 0 or frames[i - 1] != "RTCM1042")
    ]
    assert frames[:12] == ["RTCM1042"] * 12, frames[:20]
    assert frames.count("RTCM1042") == 12 * len(batches)
    assert batches == [0, 10, 20], batches  # before epochs 1, 11 and 21
    assert "waiting for a reader" in err.read_text()


def test_run_on_the_pty_gets_its_fast_fix_in_the_first_second(tmp_path):
    """`bdsfix simulate --pty` then `bdsfix run --source PTY` with an empty state directory
    (no warm start): the fast fix comes within the first 1.2 s of data (the GEOs are full
    at ~0.6 s; the 1042s come at 0.1 s and, should pyserial's flush on open have taken
    those, again at 1.1 s), the conventional one once the MEO/IGSO SOWs are decoded."""
    jsonl = tmp_path / "fixes.jsonl"
    run_err = tmp_path / "run.err"
    with _simulate(tmp_path, "--duration-s", "30") as (_sim, link, _err):
        argv = [*BDSFIX, "run", "--source", str(link), "--state-dir", str(tmp_path / "state")]
        argv += ["--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(jsonl)]
        with run_err.open("wb") as fh:
            run = subprocess.Popen(argv, cwd=ROOT, stderr=fh)
        try:

            def fixes() -> list[dict]:
                if not jsonl.exists():
                    return []
                lines = jsonl.read_text().splitlines(keepends=True)
                recs = [json.loads(x) for x in lines if x.endswith("\n")]
                return [r for r in recs if r["class"] == "FIX"]

            _wait(lambda: any(f["mode"] == "spp" for f in fixes()), "conventional fix")
        finally:
            run.terminate()
            run.wait(HANG_S)
    got = fixes()
    first_fast = next(f["since_start_s"] for f in got if f["mode"] == "fast")
    first_spp = next(f["since_start_s"] for f in got if f["mode"] == "spp")
    assert first_fast <= 1.2, got[:13]
    assert first_fast < first_spp
    assert "first fast fix: t = " in run_err.read_text()


def test_simulate_ends_at_its_duration_after_its_reader_left(tmp_path):
    """The reader takes 5 epochs and closes the device; the receiver goes on writing into
    the void (dropped, counted) and ends at --duration-s with 0: it used to block on the
    full pty for ever. --max-speed: the reader's flow control paces it while it reads."""
    with _simulate(tmp_path, "--duration-s", "60", "--max-speed") as (proc, link, err):
        frames = _frames(link, 5)
        assert proc.wait(HANG_S) == 0
    text = err.read_text()
    assert frames.count("RXM-RAWX") == 5
    assert "600 epochs" in text and "bytes lost while nobody read" in text, text
    lost = int(text.split("epochs, ")[1].split(" bytes lost")[0])
    assert lost > 100_000  # most of 600 epochs (~1 kB each) found nobody
    assert not link.exists()  # the link goes with the pty


def test_link_never_replaces_a_file(tmp_path, capsys):
    from service.commands.cli import main

    kept = tmp_path / "notes.txt"
    kept.write_text("mine")
    assert main(["simulate", "--pty", "--link", str(kept), "--duration-s", "1"]) == 3
    assert kept.read_text() == "mine"
    assert "not a symlink" in capsys.readouterr().err
