"""gpsd as a real NMEA client of ours: started on our NMEA TCP server, a JSON watcher on it.

:func:`gpsd_watching` starts ``gpsd -N -n`` on a free port with our server as its device and
connects a client, retrying until gpsd answers. A gpsd that exits (its port was taken in
the meantime) is started again on another port; one that never answers fails the test
with gpsd's own output instead of leaving the client unset. The waits only stop a hung
run (``HANG_S``); nothing here judges how fast gpsd is.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

HANG_S = 60.0
"""How long gpsd may take to answer, or to report, before the run counts as hung."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class GpsdWatch:
    """A client of gpsd with ``?WATCH`` (JSON) on: :meth:`messages` yields its reports."""

    def __init__(self, sock: socket.socket, gpsd: subprocess.Popen[bytes], log: Path) -> None:
        self.sock = sock
        self.gpsd = gpsd
        self.log = log
        self._buf = b""
        sock.sendall(b'?WATCH={"enable":true,"json":true};\n')

    def messages(self, wait_s: float = 0.05) -> list[dict]:
        """The reports that arrive within ``wait_s`` (none is an answer, not a failure)."""
        self.sock.settimeout(wait_s)
        with contextlib.suppress(TimeoutError):
            chunk = self.sock.recv(65536)
            if not chunk:
                pytest.fail(f"gpsd closed the connection: {self.output()}")
            self._buf += chunk
        *lines, self._buf = self._buf.split(b"\n")
        return [json.loads(line) for line in lines if line.strip()]

    def output(self) -> str:
        return _output_of(self.gpsd, self.log)


@contextlib.contextmanager
def gpsd_watching(device: str, *extra: str) -> Iterator[GpsdWatch]:
    """gpsd reading ``device`` (``tcp://127.0.0.1:PORT``) and a watching client."""
    with tempfile.TemporaryDirectory(prefix="bdsfix-gpsd-") as tmp:
        log = Path(tmp) / "gpsd.log"
        gpsd: subprocess.Popen[bytes] | None = None
        sock: socket.socket | None = None
        tried: list[str] = []
        deadline = time.monotonic() + HANG_S
        try:
            while sock is None:
                port = free_port()
                with log.open("wb") as fh:
                    gpsd = subprocess.Popen(
                        ["gpsd", "-N", "-n", *extra, "-S", str(port), device],
                        stdout=fh,
                        stderr=subprocess.STDOUT,
                    )
                while sock is None and gpsd.poll() is None:
                    try:
                        sock = socket.create_connection(("127.0.0.1", port), timeout=5)
                    except OSError as exc:
                        if time.monotonic() > deadline:
                            pytest.fail(
                                f"gpsd did not answer on 127.0.0.1:{port} within {HANG_S:.0f} s "
                                f"({exc}); {_output_of(gpsd, log)}"
                            )
                        time.sleep(0.1)
                if sock is None:  # gpsd exited: its port was probably taken; another port
                    tried.append(_output_of(gpsd, log))
                    if len(tried) == 3 or time.monotonic() > deadline:
                        pytest.fail("gpsd exited at start:\n" + "\n".join(tried))
            assert gpsd is not None
            yield GpsdWatch(sock, gpsd, log)
        finally:
            if sock is not None:
                sock.close()
            if gpsd is not None and gpsd.poll() is None:
                gpsd.terminate()
                try:
                    gpsd.wait(10)
                except subprocess.TimeoutExpired:
                    gpsd.kill()
                    gpsd.wait()


def _output_of(gpsd: subprocess.Popen[bytes], log: Path) -> str:
    rc = gpsd.poll()
    text = log.read_text(errors="replace")[-2000:] if log.exists() else ""
    return f"gpsd {'running' if rc is None else f'exited {rc}'}; its log:\n{text}"
