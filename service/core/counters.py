"""Event counts by name, the one counter type of every stage (exported in ZeroMQ ``STATUS``).

A plain :class:`collections.Counter` of ``str`` keys, plus :meth:`Counters.add` and
:meth:`Counters.snapshot` under a lock for counters that two threads update (a sink's
writer thread and the loop).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Any


class Counters(Counter[str]):
    """Counts by name; ``add``/``snapshot`` are safe across threads."""

    def __init__(self, iterable: Iterable[str] | Mapping[str, int] | None = None, /, **kw: Any):
        self._lock = threading.Lock()
        super().__init__(iterable, **kw)

    def add(self, key: str, n: int = 1) -> None:
        """``self[key] += n`` under the lock."""
        with self._lock:
            self[key] += n

    def snapshot(self) -> dict[str, int]:
        """A copy taken under the lock."""
        with self._lock:
            return dict(self)

    def as_dict(self) -> dict[str, int]:
        """Plain, key-sorted dict (for JSON)."""
        with self._lock:
            return {k: int(v) for k, v in sorted(self.items())}

    def __reduce__(self) -> Any:  # pickle and copy without the lock
        return (type(self), (dict(self),))


SKIP_KEYS = frozenset(
    {
        "resyncs",
        "android_bad_time",
        "android_duplicate_rows",
        "android_excess_rows",
        "duplicate_records",
        "eph_bad_prn",
        "eph_bad_toe",
        "eph_bad_week",
    }
)
SKIP_PREFIXES = ("bad_", "bytes_skipped", "decode_errors_", "map_errors_")
"""Source counter names that count damaged input (see :mod:`drivers.framing`,
:mod:`drivers.source`, :mod:`drivers.rinex`, :mod:`drivers.gnsslogger`; the ``eph_bad_*``
ephemeris messages of :mod:`drivers.rtcm` and :mod:`drivers.sbf`): with the
``*_skipped`` ones they are the "skipped input" of the summaries of ``replay``, ``run`` and
``solve`` and of every STATUS record (:func:`skipped_input`)."""


def skipped_input(counters: Mapping[str, int | float]) -> dict[str, int]:
    """The counters of ``counters`` that count damaged input dropped (:data:`SKIP_KEYS`,
    :data:`SKIP_PREFIXES`, ``*_skipped``), non-zero, by name."""
    return {
        k: int(v)
        for k, v in sorted(counters.items())
        if v and (k in SKIP_KEYS or k.startswith(SKIP_PREFIXES) or k.endswith("_skipped"))
    }
