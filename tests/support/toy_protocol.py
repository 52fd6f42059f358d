"""A toy binary protocol, to show that adding one is this module plus one registry line.

Frame: ``TY``, payload length u16 LE, payload, one check byte (the sum of every byte before
it, mod 256). Payload: GPS week u16 LE, time of week f64 LE [s], count u8, then per satellite
its RINEX ID (3 ASCII bytes) and its full B1I pseudorange f64 LE [m].
"""

from __future__ import annotations

import struct

from drivers.framing import BinaryFraming, Event, WeekContext
from service.core.counters import Counters
from service.core.types import MeasurementEpoch

SYNC = b"TY"


def _check(frame: bytes) -> bool:
    return sum(frame[:-1]) % 256 == frame[-1]


FRAMING = BinaryFraming(
    sync=SYNC,
    header_len=4,
    trailer_len=1,
    payload_len=lambda header: int.from_bytes(header[2:4], "little"),
    check=_check,
    max_payload=4096,
)


def encode(epoch: MeasurementEpoch) -> bytes:
    """One frame of ``epoch`` (its full pseudoranges)."""
    body = struct.pack("<HdB", epoch.gpst_week, epoch.gpst_tow_s, len(epoch))
    for prn, pr in zip(epoch.prn, epoch.pr_m, strict=True):
        body += prn.encode() + struct.pack("<d", pr)
    frame = SYNC + len(body).to_bytes(2, "little") + body
    return frame + bytes([sum(frame) % 256])


class ToyMapper:
    """Frames to epochs (the registry's mapper: ``ToyMapper(counters, week)``)."""

    def __init__(self, counters: Counters, week: WeekContext) -> None:
        self.counters = counters

    def on_frame(self, raw: bytes) -> list[Event]:
        week, tow_s, n = struct.unpack_from("<HdB", raw, 4)
        prn, pr = [], []
        for k in range(n):
            at = 4 + 11 + 11 * k
            prn.append(raw[at : at + 3].decode())
            pr.append(struct.unpack_from("<d", raw, at + 3)[0])
        self.counters["epochs_toy"] += 1
        return [MeasurementEpoch.from_columns(week, tow_s, prn, ["2I"] * n, pr, source="toy")]

    def flush(self) -> list[Event]:
        return []
