"""Frame-sync tracker: when each satellite's measurement becomes *full*.

A receiver knows a satellite's full pseudorange once it has decoded a SOW from that
satellite's navigation message and carries the time forward (BDS-SIS-ICD-B1I-3.0 5.2.3 for
D1, 5.3.3 for D2). GEOs (D2, 500 bps) decode a SOW every 0.6 s subframe, IGSO/MEO (D1,
50 bps) every 6 s. Until then the measurement is fractional: known modulo c*T, with T = 1 ms
after code lock (20 ms once D1 bit sync is known).

GPS L1 C/A (IS-GPS-200 20.3.2, 20.3.3.2): LNAV subframes of 6 s at 50 bps start at multiples
of 6 s of GPST, and the HOW (word 2) gives the time of week, so a GPS satellite's time is
known, like a D1 satellite's, 60 bits = 1.2 s after the preamble (``sow`` rule), but on
GPST's subframe boundaries, which lie 2 s off BDT's (GPST = BDT + 14 s). A decoded LNAV
subframe marks it known as a B1I subframe does.

Galileo I/NAV (OS SIS ICD 4.3.5): the time of week comes in the 2 s pages of word types 0, 5
and 6 (``INAV`` subframes from :mod:`service.core.gal_nav`, ``sow_s`` the GST at the page's
start); a word without a TOW says nothing of the time. After an emulated restart a Galileo
satellite becomes full at the end of the first E1-B page carrying a TOW that starts after
page sync (:func:`service.core.gal_nav.next_tow_page_start_s`, on GST = GPST).

The tracker trusts the receiver: a measurement the driver reports as full (u-blox prValid,
RINEX, RTCM with integer milliseconds) is full. After a restart, real or emulated
(``--restart-at``), every satellite is fractional again until its first SOW after the
restart, timed by the SOW-decode rule (:mod:`service.core.sow_rule`): once the SOW (words 1-2)
of the first subframe whose preamble arrives after bit sync has decoded, D2 0.12 s and D1 1.2 s
into that subframe, with the subframe boundaries in BDT as the real signal has them
(:class:`SubframeEmulator`). Under the older ``subframe`` rule a satellite becomes full at the
end of that subframe, or, when the stream carries decoded subframes, at the first one that
arrives after the restart.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from service.core.bds import nav_type, subframe_period_s
from service.core.bds_nav import SubframeHeader, subframe_start_sow_s
from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.gal_nav import next_tow_page_start_s
from service.core.gps_nav import SUBFRAME_S as LNAV_SUBFRAME_S
from service.core.gps_nav import LnavHeader
from service.core.sow_rule import DEFAULT_FULL_RULE, time_known_after_s
from service.core.systems import GnssSystem, system_of
from service.core.timebase import diff_s, gpst_to_bdt
from service.core.types import MeasurementEpoch, NavSubframe

log = logging.getLogger(__name__)

SYNC_DELAY_MIN_S = 0.1
SYNC_DELAY_MAX_S = 0.5
"""Bit-sync delay after a restart, drawn per satellite uniformly in this window [s] (an
assumed receiver behaviour: code lock and bit sync within half a second)."""


def message_of(prn: str) -> str:
    """The navigation message whose subframes give ``prn``'s time: ``LNAV`` for GPS,
    ``INAV`` for Galileo, else BeiDou's D1/D2 (:func:`service.core.bds.nav_type`)."""
    system = system_of(prn)
    if system is GnssSystem.GPS:
        return "LNAV"
    if system is GnssSystem.GAL:
        return "INAV"
    return nav_type(prn)


@dataclass(frozen=True, slots=True)
class TrackEvent:
    """A satellite's frame-sync event (ZMQ topic ``TRACK``)."""

    prn: str
    event: str  # "sow" (a SOW decoded) or "full" (measurement became full)
    gpst_week: int
    gpst_tow_s: float
    since_start_s: float
    nav_type: str  # D1, D2 (BeiDou), LNAV (GPS) or INAV (Galileo)
    # start of the subframe: BDT SOW (BeiDou), GPST tow (GPS), GST tow of the page (Galileo)
    sow_s: float | None = None
    full_since_s: float | None = None  # data time since start at which it became full


@dataclass(frozen=True, slots=True)
class SubframeEmulator:
    """Emulated SOW decoding after a restart, from the subframe boundaries of BDT.

    Each satellite needs a bit-sync delay after the restart and then waits for the next
    preamble: the first subframe that starts after sync (a receiver synced mid-subframe has
    not seen that subframe's preamble). Subframe boundaries are multiples of 0.6 s (D2) or
    6 s (D1) of BDT transmit time (ICD 5.2.2, 5.3.1), of 6 s of GPST for GPS LNAV
    (IS-GPS-200 20.3.2), seen one flight time later; a Galileo satellite waits for the next
    E1-B page carrying a TOW (:func:`service.core.gal_nav.next_tow_page_start_s`). The
    satellite's time is known ``time_known_after_s(nav_type, rule)`` after that boundary:
    rule ``sow`` once words 1-2 have decoded (D2 0.12 s, D1 1.2 s), rule ``subframe`` at the
    end of the subframe (0.6 s, 6 s).
    """

    restart_gpst_week: int
    restart_gpst_tow_s: float
    sync_delay_s: dict[str, float]
    default_sync_delay_s: float = 0.3
    rule: str = DEFAULT_FULL_RULE

    @classmethod
    def draw(
        cls,
        gpst_week: int,
        gpst_tow_s: float,
        prns: Iterable[str],
        rng: np.random.Generator,
        rule: str = DEFAULT_FULL_RULE,
    ) -> SubframeEmulator:
        """A restart at (week, tow) with a bit-sync delay per satellite drawn uniformly in
        [SYNC_DELAY_MIN_S, SYNC_DELAY_MAX_S] (the one draw every restart uses)."""
        delays = {p: float(rng.uniform(SYNC_DELAY_MIN_S, SYNC_DELAY_MAX_S)) for p in sorted(prns)}
        return cls(gpst_week, gpst_tow_s, delays, rule=rule)

    def full_mask(self, epoch: MeasurementEpoch) -> np.ndarray:
        """Which of ``epoch``'s measurements are full: reported full by the receiver and
        past their first SOW after the restart."""
        full = np.isfinite(epoch.pr_m)
        for i, prn in enumerate(epoch.prn):
            if full[i]:
                w, t = self.full_at_tow_s(prn, float(epoch.pr_m[i]))
                full[i] = diff_s(epoch.gpst_week, epoch.gpst_tow_s, w, t) >= 0
        return full

    def full_at_tow_s(self, prn: str, pr_m: float) -> tuple[int, float]:
        """GPST (week, tow) at which ``prn``'s time is first known after the restart."""
        message = message_of(prn)
        known_s = time_known_after_s(message, self.rule)
        flight_s = pr_m / C_M_S if math.isfinite(pr_m) else NOMINAL_FLIGHT_TIME_S
        delay = self.sync_delay_s.get(prn, self.default_sync_delay_s)
        if message == "INAV":  # pages on GST (= GPST to tens of ns, OS SIS ICD 5.1.8)
            tx_sync = self.restart_gpst_tow_s + delay - flight_s
            start = next_tow_page_start_s(tx_sync)
            known_rx = start + known_s + flight_s
            return self.restart_gpst_week, known_rx
        if message == "LNAV":  # subframes on GPST
            period, t_sys = LNAV_SUBFRAME_S, self.restart_gpst_tow_s
        else:  # on BDT
            period = subframe_period_s(prn)
            _, t_sys = gpst_to_bdt(self.restart_gpst_week, self.restart_gpst_tow_s)
        tx_sync = t_sys + delay - flight_s  # transmit time of the first synced bit
        start = math.ceil(round(tx_sync / period, 9)) * period  # the next preamble
        known_rx = start + known_s + flight_s
        return self.restart_gpst_week, self.restart_gpst_tow_s + (known_rx - t_sys)


class FrameSyncTracker:
    """Per-satellite frame sync; turns driver epochs into the engine's view of full/fractional."""

    def __init__(self) -> None:
        self._start: tuple[int, float] | None = None
        self._full_since_s: dict[str, float] = {}  # satellites full now, since when
        self._restart: tuple[int, float] | None = None
        self._emulator: SubframeEmulator | None = None
        self._sow_after_restart: set[str] = set()
        self.seen_subframes = False

    # --- time --------------------------------------------------------------------------
    def since_start_s(self, week: int, tow_s: float) -> float:
        ref = self._restart or self._start
        return 0.0 if ref is None else diff_s(week, tow_s, *ref)

    def restart(
        self, gpst_week: int, gpst_tow_s: float, emulator: SubframeEmulator | None = None
    ) -> None:
        """Forget all frame sync at this instant (receiver restart)."""
        log.info(
            "restart at GPST %d/%.3f: all satellites fractional until SOW", gpst_week, gpst_tow_s
        )
        self._restart = (gpst_week, gpst_tow_s)
        self._emulator = emulator
        self._full_since_s.clear()
        self._sow_after_restart.clear()

    # --- inputs ------------------------------------------------------------------------
    def on_subframe(self, sf: NavSubframe) -> list[TrackEvent]:
        """A decoded subframe: its SOW makes the satellite's time known."""
        self.seen_subframes = True
        if self._start is None:
            self._start = (sf.gpst_week, sf.gpst_tow_s)
        if sf.nav_type == "INAV" and sf.sow_s < 0:
            return []  # a word without a time of week (ICD 4.3.5)
        self._sow_after_restart.add(sf.prn)
        since = self.since_start_s(sf.gpst_week, sf.gpst_tow_s)
        if sf.nav_type == "INAV":
            start_s = float(sf.sow_s)
        elif sf.nav_type == "LNAV":  # the HOW's time is the next subframe's (IS-GPS-200 20.3.3.2)
            start_s = LnavHeader(sf.fra_id, int(sf.sow_s)).start_tow_s
        else:
            start_s = subframe_start_sow_s(
                SubframeHeader(sf.fra_id, int(sf.sow_s), sf.page), sf.nav_type
            )
        return [
            TrackEvent(
                prn=sf.prn,
                event="sow",
                gpst_week=sf.gpst_week,
                gpst_tow_s=sf.gpst_tow_s,
                since_start_s=since,
                nav_type=sf.nav_type,
                sow_s=start_s,
                full_since_s=self._full_since_s.get(sf.prn),
            )
        ]

    def on_epoch(self, epoch: MeasurementEpoch) -> tuple[MeasurementEpoch, list[TrackEvent]]:
        """The epoch as the engine should see it, and TRACK events for satellites gone full."""
        if self._start is None:
            self._start = (epoch.gpst_week, epoch.gpst_tow_s)
        week, tow = epoch.gpst_week, epoch.gpst_tow_s
        full = np.isfinite(epoch.pr_m)
        restricted = self._restart is not None and diff_s(week, tow, *self._restart) >= 0
        if restricted:
            emulator = self._emulator
            # decoded subframes arrive at their end: under the SOW rule the satellite's time
            # was known before, at the instant the emulator gives from BDT
            if emulator is not None and (emulator.rule == "sow" or not self.seen_subframes):
                full = emulator.full_mask(epoch)
            else:
                full &= np.array([p in self._sow_after_restart for p in epoch.prn], dtype=bool)
        events: list[TrackEvent] = []
        since = self.since_start_s(week, tow)
        for prn, is_full in zip(epoch.prn, full.tolist(), strict=True):
            if is_full and prn not in self._full_since_s:
                self._full_since_s[prn] = since
                events.append(
                    TrackEvent(
                        prn=prn,
                        event="full",
                        gpst_week=week,
                        gpst_tow_s=tow,
                        since_start_s=since,
                        nav_type=message_of(prn),
                        full_since_s=since,
                    )
                )
            elif not is_full and prn in self._full_since_s:
                del self._full_since_s[prn]  # lost lock or time: fractional again
        # full unless the restart holds some back: the receiver's own view, as it came
        if not restricted or full.all() or np.array_equal(full, np.isfinite(epoch.pr_m)):
            return epoch, events
        ct = C_M_S * epoch.period_s
        frac = np.where(np.isfinite(epoch.frac_pr_m), epoch.frac_pr_m, np.mod(epoch.pr_m, ct))
        return replace(epoch, pr_m=np.where(full, epoch.pr_m, np.nan), frac_pr_m=frac), events
