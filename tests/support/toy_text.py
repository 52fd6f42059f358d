"""A toy text file format, to show that adding one is this module plus one registry line.

First line ``TOYTEXT 1``; then one line per measurement: GPS week, time of week [s], RINEX
satellite ID and full B1I pseudorange [m], blank-separated. Consecutive lines of one time
are one epoch.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from service.core.counters import Counters
from service.core.types import MeasurementEpoch

MAGIC = b"TOYTEXT 1"


def detect(path: Path, head: bytes) -> bool:
    return head.startswith(MAGIC)


def write(path: Path, epochs: list[MeasurementEpoch]) -> None:
    with path.open("w") as fh:
        fh.write(MAGIC.decode() + "\n")
        for e in epochs:
            for prn, pr in zip(e.prn, e.pr_m, strict=True):
                fh.write(f"{e.gpst_week} {float(e.gpst_tow_s)!r} {prn} {float(pr)!r}\n")


def events(
    path: Path, counters: Counters, lenient: bool, systems: frozenset[str]
) -> Iterator[MeasurementEpoch]:
    """The registry's reader."""

    def epoch(key: tuple[int, float], rows: list[tuple[str, float]]) -> MeasurementEpoch:
        counters["epochs_toytext"] += 1
        prn = [p for p, _ in rows]
        return MeasurementEpoch.from_columns(*key, prn, ["2I"] * len(prn), [r for _, r in rows])

    with path.open() as fh:
        fh.readline()
        key, rows = None, []
        for line in fh:
            week, tow, prn, pr = line.split()
            k = (int(week), float(tow))
            if rows and k != key:
                yield epoch(key, rows)
                rows = []
            key = k
            rows.append((prn, float(pr)))
        if rows:
            yield epoch(key, rows)
