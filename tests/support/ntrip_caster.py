"""A real NTRIP caster on loopback for the tests: pygnssutils' own caster (its
``SocketServer`` in NTRIP caster mode, ``ntripmode=1``, with its user and password), run as
a separate process so that a test can kill it (SIGKILL, as a crash) and start it again on
the same port.

It serves the RTCM 3 frames of a file on pygnssutils' one mountpoint (``/pygnssutils``),
over and over, one frame at a time, the whole file every ``--cycle-s`` seconds: a caster
relaying a base station repeats its ephemerides in the same way. pygnssutils' caster sends
a client what it is given after the client connected (nothing older).

``python -m tests.support.ntrip_caster --port P --user U --password W --rtcm FILE`` prints
``caster listening on 127.0.0.1:P`` once it accepts connections.
"""

from __future__ import annotations

import argparse
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import TracebackType

from tests.support.paths import ROOT

MOUNT = "pygnssutils"
"""The one mountpoint pygnssutils' caster serves (``pygnssutils.globals.PYGPSMP``)."""
READY = "caster listening on"
HANG_S = 60.0
USER = "bdsfix"
PASSWORD = "secret"  # noqa: S105 - the test caster's password


def rtcm_frames(path: str | Path) -> list[bytes]:
    """The RTCM 3 frames of a file (pyrtcm's reader)."""
    from pyrtcm import RTCMReader

    with open(path, "rb") as fh:
        return [raw for raw, _msg in RTCMReader(fh)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    from pygnssutils.globals import CLIAPP
    from pygnssutils.socket_server import ClientHandler, SocketServer

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--user", default=USER)
    p.add_argument("--password", default=PASSWORD)
    p.add_argument("--rtcm", required=True, help="file of RTCM 3 frames to serve")
    p.add_argument("--cycle-s", type=float, default=1.0, help="the whole file every this long")
    p.add_argument("--version", default="2.0", choices=("1.0", "2.0"), help="NTRIP version")
    args = p.parse_args(argv)
    frames = rtcm_frames(args.rtcm)
    if not frames:
        raise SystemExit(f"{args.rtcm}: no RTCM 3 frame")
    mq: queue.Queue[bytes] = queue.Queue()

    def feed() -> None:
        gap_s = args.cycle_s / len(frames)
        while True:
            for raw in frames:
                mq.put(raw)
                time.sleep(gap_s)

    with SocketServer(
        CLIAPP,
        1,  # NTRIP caster mode
        5,
        mq,
        ("127.0.0.1", args.port),
        ClientHandler,
        ntripversion=args.version,
        ntripuser=args.user,
        ntrippassword=args.password,
    ) as server:
        threading.Thread(target=feed, daemon=True).start()
        print(f"{READY} 127.0.0.1:{args.port}", flush=True)
        server.serve_forever()
    return 0


class Caster:
    """The caster as a subprocess: ``start()``, ``kill()`` (SIGKILL) and ``start()`` again
    on the same port; a context manager that kills it at the end."""

    def __init__(
        self,
        rtcm: str | Path,
        *,
        user: str = USER,
        password: str = PASSWORD,
        cycle_s: float = 1.0,
        version: str = "2.0",
        log_path: Path | None = None,
    ) -> None:
        self.port = free_port()
        self.argv = [sys.executable, "-m", "tests.support.ntrip_caster"]
        self.argv += ["--port", str(self.port), "--user", user, "--password", password]
        self.argv += ["--rtcm", str(rtcm), "--cycle-s", str(cycle_s), "--version", version]
        self.log_path = log_path
        self.proc: subprocess.Popen[str] | None = None
        self.starts = 0

    def url(self, user: str = USER, password: str = PASSWORD) -> str:
        return f"ntrip://{user}:{password}@127.0.0.1:{self.port}/{MOUNT}"

    def start(self) -> None:
        """Start and wait for its ready line (only a hung start fails, after HANG_S)."""
        err = self.log_path.open("a") if self.log_path else subprocess.DEVNULL
        try:
            self.proc = subprocess.Popen(
                self.argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True
            )
        finally:
            if self.log_path:
                err.close()  # type: ignore[union-attr]
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # blocks until ready or exit
        assert line.startswith(READY), f"caster did not start: {line!r}"
        self.starts += 1

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=HANG_S)
        if self.proc is not None and self.proc.stdout is not None:
            self.proc.stdout.close()
        self.proc = None

    def __enter__(self) -> Caster:
        self.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.kill()


if __name__ == "__main__":
    sys.exit(main())
