"""Ephemerides from the network (``nav = ["ntrip://..."]``): what enters the store, and when.

A caster relays what a base station decodes, repeated every few seconds; the daemon takes
only the broadcast ephemerides from it (the base station's own measurements, RTCM MSM, are
not the receiver's and never reach the pipeline) and judges each set by the receiver's time:

- a set whose t_oe is further than ``max_age_s`` from the time of the receiver's latest
  measurement epoch is refused as stale (counted ``ntrip_stale``; one WARNING per satellite
  per minute): a caster replaying an old stream, or a base station whose receiver has
  stopped, cannot fill the store with sets no fix may use (ICD B1I 5.2.4.9: a set is
  broadcast hourly and used near its t_oe);
- until the receiver has given a time, sets are held (at most :data:`MAX_HELD` per
  satellite, the newest t_oe) and judged by the first epoch's time before that epoch is
  solved: a receiver that has decoded nothing gets its fast fix as soon as its GEOs are full;
- a set equal to the one last judged for its satellite (taken or refused) is not judged
  again (a caster repeats its sets every few seconds: ``ntrip_repeats``);
- a set taken is marked ``source = "ntrip"`` (the store's counters: ``ephemeris_ntrip``).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

from service.core.ratelog import RateLimitedLog
from service.core.timebase import bdt_to_gpst, diff_s
from service.core.types import UNKNOWN_WEEK, Ephemeris

log = logging.getLogger(__name__)

MAX_HELD = 4
"""Sets held per satellite while the receiver has given no time."""
SOURCE = "ntrip"


@dataclass(frozen=True, slots=True)
class Networked:
    """An event that came from a network nav source (not from the receiver)."""

    event: object
    source: str  # the redacted URL


class NetNavGate:
    """Judges network ephemerides by age against the receiver's time (see the module)."""

    def __init__(self, max_age_s: float) -> None:
        self.max_age_s = max_age_s
        self.counters: dict[str, int] = {}
        self._time: tuple[int, float] | None = None  # GPST of the latest receiver epoch
        self._held: dict[str, list[Ephemeris]] = {}
        self._last: dict[str, Ephemeris] = {}
        self._log = RateLimitedLog(log)

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def offer(self, eph: Ephemeris, source: str = "") -> list[Ephemeris]:
        """The sets to add to the store now (``eph`` or none)."""
        if self._last.get(eph.prn) == dataclasses.replace(eph, source=SOURCE):
            self._count("ntrip_repeats")
            return []
        if self._time is None:
            held = self._held.setdefault(eph.prn, [])
            held[:] = [e for e in held if (e.week, e.toe_sow_s) != (eph.week, eph.toe_sow_s)]
            held.append(eph)
            held.sort(key=lambda e: (e.week, e.toe_sow_s))
            del held[:-MAX_HELD]
            return []
        return self._judge([eph], source)

    def on_epoch(self, gpst_week: int, gpst_tow_s: float) -> list[Ephemeris]:
        """The receiver's time moved to a new epoch: the held sets judged by it (once)."""
        if gpst_week == UNKNOWN_WEEK:
            return []
        self._time = (gpst_week, gpst_tow_s)
        if not self._held:
            return []
        held = [e for sets in self._held.values() for e in sets]
        self._held.clear()
        return self._judge(held, "")

    def _judge(self, ephs: list[Ephemeris], source: str) -> list[Ephemeris]:
        if self._time is None:
            return []
        out = []
        for eph in ephs:
            taken = dataclasses.replace(eph, source=SOURCE)
            self._last[eph.prn] = taken
            age_s = diff_s(*self._time, *bdt_to_gpst(eph.week, eph.toe_sow_s))
            if abs(age_s) > self.max_age_s:
                self._count("ntrip_stale")
                self._log.warning(
                    eph.prn,
                    "nav %s: ephemeris %s (BDT week %d, t_oe %.0f s) is %.1f h %s the "
                    "receiver's time: refused as stale (ntrip_max_age_s %.0f s); is the "
                    "caster's stream current?",
                    source or "ntrip",
                    eph.prn,
                    eph.week,
                    eph.toe_sow_s,
                    abs(age_s) / 3600.0,
                    "before" if age_s > 0 else "after",
                    self.max_age_s,
                )
                continue
            self._count("ntrip_ephemerides")
            out.append(taken)
        return out
