"""A device on a real pty that talks and never answers a u-blox set-up: NMEA at the pace of
115200 baud, random bytes at that pace, or one UBX header claiming a 65,535-byte payload
followed by a trickle of a byte every 10 ms (never 50 ms of silence; the header is sent again
every 0.5 s, as a set-up empties its input buffer before each message). A thread serves the
pty's master: it writes what the kind says and reads (and drops) what the set-up sends.
Timeouts here only stop a hung test (``HANG_S``)."""

from __future__ import annotations

import contextlib
import functools
import operator
import os
import random
import select
import threading
import time
import tty
from collections.abc import Iterator

HANG_S = 120.0
BAUD_BYTES_S = 11_520
"""115200 baud, 8N1: 11,520 bytes a second."""
TICK_S = 0.01
KINDS = ("nmea", "garbage", "ubx-trickle")


def _nmea(body: str) -> bytes:
    """One NMEA 0183 sentence: ``$``, the body, ``*`` and the XOR of the body's bytes."""
    check = functools.reduce(operator.xor, body.encode("ascii"), 0)
    return f"${body}*{check:02X}\r\n".encode("ascii")


NMEA_BURST = b"".join(
    _nmea(body)
    for body in (
        "GNGGA,031500.00,2219.19100,N,11412.54600,E,1,12,0.8,60.0,M,-2.5,M,,",
        "GNGSA,A,3,01,02,03,04,05,06,07,08,09,10,11,12,1.4,0.8,1.1,4",
        "GBGSV,3,1,12,01,45,120,40,02,38,230,39,03,60,190,42,04,30,110,38,1",
        "GNRMC,031500.00,A,2219.19100,N,11412.54600,E,0.0,,100621,,,A,V",
        "GNVTG,,T,,M,0.0,N,0.0,K,A",
    )
)


def _chunks(kind: str, seed: int) -> Iterator[bytes]:
    """What the device sends every TICK_S."""
    per_tick = round(BAUD_BYTES_S * TICK_S)
    if kind == "nmea":
        stream = NMEA_BURST * (per_tick // len(NMEA_BURST) + 2)
        offset = 0
        while True:
            yield (stream[offset:] + stream[:offset])[:per_tick]
            offset = (offset + per_tick) % len(NMEA_BURST)
    elif kind == "garbage":
        rng = random.Random(seed)
        while True:
            yield rng.randbytes(per_tick)
    elif kind == "ubx-trickle":
        # RXM-RAWX (0x02 0x15) claiming 65,535 bytes, then one byte a tick; the header again
        # every 50 ticks, so that a reader that emptied its input buffer hears one
        while True:
            yield b"\xb5\x62\x02\x15\xff\xff"
            for _ in range(49):
                yield b"\x00"
    else:
        raise ValueError(kind)


@contextlib.contextmanager
def talking_device(kind: str, seed: int = 0) -> Iterator[str]:
    """A raw pty whose device side hears ``kind`` (see :data:`KINDS`); yields its path."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    stop = threading.Event()

    def serve() -> None:
        chunks = _chunks(kind, seed)
        next_t = time.monotonic()
        while not stop.is_set():
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(master, next(chunks))  # a full pty drops it: nobody reads
            next_t += TICK_S
            while (wait := next_t - time.monotonic()) > 0 and not stop.is_set():
                ready, _, _ = select.select([master], [], [], wait)
                if ready:
                    with contextlib.suppress(BlockingIOError, OSError):
                        os.read(master, 4096)  # what the set-up sends: never answered

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield os.ttyname(slave)
    finally:
        stop.set()
        thread.join(HANG_S)
        os.close(master)
        os.close(slave)
