"""The time-to-first-fix timeline of a stream: the data time since the first measurement (or
since an emulated restart) of the first GEO and non-GEO satellite whose SOW is known (its
measurement became full), the first fast fix and the first conventional fix.

One place for it: ``replay`` and ``run`` print it at the end from the pipeline's results
(:meth:`Timeline.marks`), the status page (:mod:`service.output.sinks.http_page`) shows it
live from the records the outputs get (:meth:`Timeline.on_record`); both give the same
figures for the same stream.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from service.core.systems import system_of

FIRST_GEO_SOW = "first GEO SOW decoded"
FIRST_FAST = "first fast fix"
FIRST_NON_GEO_SOW = "first non-GEO SOW decoded"
FIRST_SPP = "first conventional fix"
ORDER = (FIRST_GEO_SOW, FIRST_FAST, FIRST_NON_GEO_SOW, FIRST_SPP)
"""The timeline's events in the order the status page shows them."""
FULL4 = "first 4 full ranges"
"""The first epoch with at least 4 full ranges of any system (4 satellites' time of week
known): from then on a conventional receiver can fix, geometry and ephemerides permitting.
The built-in scenario reaches it with its 4 GEOs at 0.70 s, whose geometry alone does not
allow an SPP fix; the Perth phone log with 9 GPS satellites at 12.00 s. The summaries show
it (from the epochs, :meth:`Timeline.marks`); the records do not carry every system's full
ranges, so the page does not."""
SUMMARY_ORDER = (FIRST_GEO_SOW, FIRST_FAST, FIRST_NON_GEO_SOW, FULL4, FIRST_SPP)
"""The timeline's events in the order the summaries print them."""

_FIX_KEYS = {"fast": FIRST_FAST, "spp": FIRST_SPP}
_NOT_IN_ORDER = frozenset({"no_time", "out_of_order"})
"""Declines of epochs the pipeline left out of the stream's time (no week, a step back)."""


class Timeline:
    """First events of a stream since its start or its (emulated) restart."""

    def __init__(self, offset_s: float = 0.0) -> None:
        self.first: dict[str, float] = {}
        self.offset_s = offset_s
        """Added to every figure shown (the built-in scenario's first epoch comes
        ``offset_s`` after the virtual receiver's start)."""
        self._latest_s = -float("inf")  # records: the latest data time seen since the start
        self.restarted = False
        """Records: the timeline started again (data time since the start went back)."""
        self.waits: str | None = None
        """Why the epoch of :data:`FULL4` had no fix (its full ranges by system and its
        decline reason), if it had none."""

    def mark(self, key: str, t_s: float) -> bool:
        """Note ``key`` at ``t_s`` unless already noted; True when it is new."""
        if key in self.first:
            return False
        self.first[key] = t_s
        return True

    def on_result(self, r: Any) -> None:
        """Mark the first events a :class:`service.engine.pipeline.EpochResult` brings."""
        self.marks(r)

    def marks(self, r: Any) -> list[str]:
        """Mark the first events of an EpochResult; the keys that are new. A satellite's
        SOW counts as decoded when its measurement became full (``r.track``)."""
        if r.restarted:  # the timeline is the restarted receiver's
            self.first.clear()
            self.waits = None
        new = []
        for ev in r.track:
            key = FIRST_GEO_SOW if ev.nav_type == "D2" else FIRST_NON_GEO_SOW
            if self.mark(key, ev.since_start_s):
                new.append(key)
        if r.since_start_s is None:
            return new
        fix_key = _FIX_KEYS.get(r.fix.mode)
        if fix_key and self.mark(fix_key, r.since_start_s):
            new.append(fix_key)
        full = int(np.isfinite(r.epoch.pr_m).sum())
        if full >= 4 and self.mark(FULL4, r.since_start_s):
            new.append(FULL4)
            if not r.fix.ok:
                full_prns = [
                    p for p, pr in zip(r.epoch.prn, r.epoch.pr_m, strict=True) if math.isfinite(pr)
                ]
                by_system = Counter(system_of(p).name for p in full_prns)
                systems = ", ".join(f"{name} {n}" for name, n in sorted(by_system.items()))
                self.waits = f"({systems} full): {r.fix.reason}"
        return new

    def on_record(self, cls: str, rec: Mapping[str, Any]) -> bool:
        """Mark what a record brings: a ``TRACK`` ``full`` event (a SOW known), a ``FIX``
        of mode fast or spp. The records carry no restart flag: data time since the start
        going back (on a ``full`` event or a fix of the stream) is the restart, and the
        timeline starts again. True when the timeline changed."""
        t_s = rec.get("since_start_s")
        if t_s is None:
            return False
        if cls == "TRACK":
            if rec.get("event") != "full":
                return False
            key: str = FIRST_GEO_SOW if rec.get("nav_type") == "D2" else FIRST_NON_GEO_SOW
        elif cls == "FIX":
            if rec.get("reason_code") in _NOT_IN_ORDER:
                return False
            key = _FIX_KEYS.get(str(rec.get("mode")), "")  # "" for none
        else:
            return False
        changed = False
        if t_s < self._latest_s:
            self.first.clear()
            self.restarted = changed = True
        self._latest_s = t_s
        return (bool(key) and self.mark(key, t_s)) or changed

    def figures(self) -> dict[str, float | None]:
        """Each event of :data:`ORDER` and its time [s, with the offset], None if not reached."""
        return {
            k: round(self.first[k] + self.offset_s, 6) if k in self.first else None for k in ORDER
        }

    def texts(self) -> dict[str, str]:
        """Each event of :data:`ORDER` as :meth:`lines` writes its figure."""
        return {
            k: figure_text(self.first[k] + self.offset_s if k in self.first else None)
            for k in ORDER
        }

    def lines(self, offset_s: float | None = None, restarted: bool = False) -> list[str]:
        """The timeline as the summary prints it."""
        since = "the emulated restart" if restarted else "the first measurement"
        off = self.offset_s if offset_s is None else offset_s
        lines = [f"  timeline (t: data time since {since}):"] + [
            f"  {k:<28} {figure_text(self.first[k] + off if k in self.first else None)}"
            for k in SUMMARY_ORDER
        ]
        if self.waits is not None:
            lines.append(f"  no fix at {FULL4} {self.waits}")
        return lines


def figure_text(t_s: float | None) -> str:
    """One figure of the timeline as the summaries and the status page write it."""
    return "(not reached)" if t_s is None else f"t = {t_s:6.2f} s"
