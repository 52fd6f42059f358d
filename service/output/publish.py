"""Publishers: the fan-out the receiver loop talks to, over a list of sinks
(:mod:`service.output.sinks`). None of it blocks.

Each sink gets what it declares it takes, in this order per epoch: RMC, VTG and GGA to the
live NMEA sinks (as soon as they are built), the TRACK records held since the last release
(the subframes decoded just before the epoch, the satellites it found full), the FIX record,
the epoch's other sentences to the live NMEA sinks, then all of the epoch's sentences to the
epoch-wise NMEA sinks (files).

TRACK records are held, not sent as their events come, until the next fix has its lead
sentences out, a STATUS, :meth:`Publishers.release_tracks` (the receiver loop calls it when
it has caught up with its source) or the close: every record sink sees them in the order it
always did (before the FIX of the epoch that followed their subframes), and the JSON and
ZeroMQ work of an epoch's subframes no longer sits between its last byte and its GGA.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

from service.core.counters import Counters
from service.core.types import Fix, ReceiverFix, SatView
from service.output.nmea import fix_utc, lead_sentences, sentences_after_gga
from service.output.records import fix_record, sky_record, status_record, track_record_of
from service.output.sinks.base import RECORD_CLASSES, Sink

log = logging.getLogger(__name__)


class Publishers:
    """Fan-out of fixes, SKY, TRACK and STATUS to a list of sinks, in their order.

    Each record class goes to the sinks that take it (ZeroMQ: all four; JSONL: FIX and
    TRACK); each fix's NMEA to the NMEA sinks, with the GSV of the sky it carries. NMEA
    time is the fix's own time: the receiver's time tag minus the solved clock bias.
    """

    def __init__(
        self,
        sinks: Sequence[Sink] = (),
        *,
        talker: str = "GN",
        gsa_talker: str | None = None,
    ) -> None:
        self.sinks = tuple(sinks)
        self.talker = talker
        self.gsa_talker = gsa_talker
        self.counters = Counters()
        self._time_known = False
        self.gga_out_s = 0.0
        """:func:`time.perf_counter` when the last epoch's lead sentences (RMC, VTG, GGA)
        were handed to the live NMEA sinks: where the latency path ends in the daemon
        (``bench/bench_latency.py``)."""
        self._nmea_live = [s for s in self.sinks if s.nmea == "live"]
        self._nmea_epoch = [s for s in self.sinks if s.nmea == "epoch"]
        self._takes = {c: [s for s in self.sinks if c in s.records] for c in RECORD_CLASSES}
        self._held_tracks: list[Any] = []

    def fix(
        self,
        fix: Fix,
        since_start_s: float | None = None,
        sky: Callable[[Fix], tuple[SatView, ...]] | None = None,
        receiver_fix: ReceiverFix | None = None,
    ) -> Fix:
        """Publish one solver's result for one epoch (FIX record and NMEA); the receiver's
        own fix, when given, rides on the FIX record (``receiver_fix``).

        The latency path goes first: RMC, VTG and GGA to the live NMEA sinks (TCP, serial)
        as soon as they are built, then the FIX record (ZeroMQ, then JSONL), then the other
        sentences. NMEA files and stdout get the epoch's sentences as one block after its
        JSONL line.
        ``sky``, when given, computes the satellites in view (for GSV) once GGA is out; the
        fix is returned with them."""
        self.counters[f"published_{fix.mode}"] += 1
        if fix.ok:
            self._time_known = True
        nmea = bool(self._nmea_live or self._nmea_epoch)
        if nmea:
            utc = fix_utc(fix)
            lead = b"".join(
                lead_sentences(fix, utc=utc, talker=self.talker, gsa_talker=self.gsa_talker)
            )
            for sink in self._nmea_live:
                sink.write_nmea(lead)
            self.gga_out_s = time.perf_counter()
        self.release_tracks()
        if self._takes["FIX"]:
            rec = fix_record(fix, since_start_s, receiver_fix)
            for sink in self._takes["FIX"]:
                sink.write_record("FIX", rec)
        if sky is not None and fix.ok and not fix.sky:
            fix = replace(fix, sky=sky(fix))
        if nmea:
            rest = b"".join(
                sentences_after_gga(
                    fix,
                    utc=utc,
                    talker=self.talker,
                    time_known=self._time_known,
                    gsa_talker=self.gsa_talker,
                )
            )
            for sink in self._nmea_live:
                sink.write_nmea(rest)
            for sink in self._nmea_epoch:
                sink.write_nmea(lead + rest)
        return fix

    def sky(self, gpst_week: int, gpst_tow_s: float, sats: Sequence[SatView]) -> None:
        """Publish the satellites in view (``SKY``)."""
        if self._takes["SKY"]:
            rec = sky_record(gpst_week, gpst_tow_s, sats)
            for sink in self._takes["SKY"]:
                sink.write_record("SKY", rec)

    def epoch(self, result: Any) -> None:
        """A :class:`service.engine.pipeline.EpochResult`: its fix, then its sky when it has one."""
        fix = self.fix(
            result.fix,
            result.since_start_s,
            getattr(result, "sky", None),
            getattr(result, "receiver_fix", None),
        )
        if fix.sky:
            self.sky(fix.gpst_week, fix.gpst_tow_s, fix.sky)

    def track(self, event: Any) -> None:
        """A :class:`service.engine.tracker.TrackEvent` as a ``TRACK`` record, held until
        the next release (module docstring)."""
        if self._takes["TRACK"]:
            self._held_tracks.append(event)

    def release_tracks(self) -> None:
        """Send the TRACK records held, in the order their events came."""
        held, self._held_tracks = self._held_tracks, []
        for event in held:
            rec = track_record_of(event)
            for sink in self._takes["TRACK"]:
                sink.write_record("TRACK", rec)

    def all_counters(self, counters: Mapping[str, int | float] | None = None) -> Counters:
        """``counters`` merged with those of the fan-out and of every sink."""
        merged = Counters()
        merged.update(dict(counters or {}))
        merged.update(self.counters)
        for sink in self.sinks:
            merged.update(dict(sink.counters()))
        return merged

    def status(self, counters: Mapping[str, int | float], **extra: Any) -> None:
        """Publish a ``STATUS`` record of all counters (after the TRACK records held)."""
        self.release_tracks()
        if self._takes["STATUS"]:
            rec = status_record(self.all_counters(counters), **extra)
            for sink in self._takes["STATUS"]:
                sink.write_record("STATUS", rec)

    def gone(self) -> bool:
        """True when every sink is gone (pipes whose readers have left, as in
        ``replay | head``): nothing published from now on can reach anyone."""
        return bool(self.sinks) and all(sink.gone() for sink in self.sinks)

    def reopen(self) -> None:
        """Reopen file outputs (SIGHUP after log rotation)."""
        for sink in self.sinks:
            sink.reopen()

    def close(self) -> None:
        self.release_tracks()
        for sink in self.sinks:
            sink.close()
