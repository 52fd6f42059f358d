"""A live receiver that sends nothing recognisable (wrong protocol or baud rate: here random
bytes on a real pty) gets a warning once per ``silence_warn_s`` while it lasts, and the
daemon keeps reading until it is stopped."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import tty

from tests.support.paths import ROOT


def test_a_silent_receiver_is_warned_about_once_per_interval_and_read_on(tmp_path):
    master, slave = os.openpty()
    tty.setraw(slave)
    device = tmp_path / "ttyRX"
    device.symlink_to(os.ttyname(slave))
    cmd = [sys.executable, "-m", "service", "run", "--source", str(device)]
    cmd += ["--state-dir", str(tmp_path / "state"), "--nmea-tcp", "", "--zmq", ""]
    cmd += ["--silence-warn-s", "1", "--status-interval-s", "3600"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    stop = threading.Event()

    def noise() -> None:  # bytes that never make a frame: no UBX/RTCM/NMEA sync byte
        rng = random.Random(7)
        alphabet = bytes(b for b in range(256) if b not in (0xB5, 0xD3, ord("$"), ord("#")))
        while not stop.wait(0.05):
            try:
                os.write(master, bytes(rng.choice(alphabet) for _ in range(64)))
            except OSError:
                return

    writer = threading.Thread(target=noise, daemon=True)
    writer.start()
    hung = threading.Timer(120.0, proc.kill)  # only stops a hung run
    hung.start()
    warnings = []
    try:
        for line in proc.stderr:
            if "nothing recognisable" in line:
                warnings.append(line)
                if len(warnings) == 2:
                    break
        proc.send_signal(signal.SIGTERM)
        rest = proc.communicate(timeout=60)[1]
    finally:
        hung.cancel()
        stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)
    assert len(warnings) == 2, rest
    assert all(w.startswith("WARNING ") and "still reading" in w for w in warnings)
    assert proc.returncode == 0 and "Traceback" not in rest
