"""Incremental framer for byte streams that mix the registered protocols, plus shared driver
state (counters, the GPS week context).

The framer knows no protocol: it matches each candidate by sync pattern against the
:class:`Framing` of the protocols registered (:data:`drivers.protocols.PROTOCOLS`), which
measure the frame there. Protocols may share a first byte (SBF ``$@`` and NMEA ``$``): the
longest sync is tried first, and only two protocols with the same sync are refused.
:class:`BinaryFraming` describes the usual binary layout (sync bytes, header with a length
field, payload, check trailer) as data. Besides frames the
framer takes gpsd regression-log comments: a ``#`` at the start of a line, printable text up
to the newline; a valid frame that ends such a line ends the comment where it starts.

The framer never blocks and never trusts a claimed length: lengths are bounded, and after a
failed check it advances one byte, not the claimed length, so a false header cannot swallow
the valid frames that follow it. Memory is bounded by the longest allowed frame.

Counter keys, ``<p>`` being a registered protocol name (``ubx``, ``rtcm``, ``nmea``):
``bytes_in``, ``frames_<p>``, ``comment_lines``, ``comment_bytes``, ``bytes_skipped``,
``resyncs``, ``bad_checksum_<p>``, ``bad_length_<p>``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

from service.core.constants import WEEK_S
from service.core.counters import Counters
from service.core.ratelog import RateLimitedLog
from service.core.timebase import (
    MIN_SANE_GPS_WEEK,
    diff_s,
    nearest_week,
    normalize,
    system_clock_gps_week,
)
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    ReceiverFix,
    TimeOffset,
)

log = logging.getLogger(__name__)

Event = MeasurementEpoch | NavSubframe | Ephemeris | KlobucharParams | ReceiverFix | TimeOffset
"""What drivers emit: the event types of :mod:`service.core.types`."""

DEFAULT_MAX_COMMENT = 8192

# What Framing.measure returns besides a frame size (> 0).
NOT_A_FRAME = 0
NEED_MORE = -1
BAD_LENGTH = -2
BAD_CHECKSUM = -3


@dataclass(frozen=True, slots=True)
class Frame:
    """One complete, check-valid frame: its protocol name, bytes, and offset in the stream."""

    protocol: str
    raw: bytes
    offset: int


class Framing(Protocol):
    """How the frames of one protocol are recognised in a byte stream."""

    @property
    def sync(self) -> bytes:
        """The bytes every frame starts with; a longer sync is tried before a shorter one
        that starts with the same byte."""
        ...

    @property
    def max_payload(self) -> int:
        """Default bound of the payload length a frame may have [bytes]."""
        ...

    def measure(self, buf: bytes | bytearray, pos: int, max_payload: int) -> int:
        """Size of the valid frame starting at ``buf[pos]`` [bytes], or :data:`NEED_MORE`
        (a candidate that the bytes so far neither complete nor refute), :data:`NOT_A_FRAME`,
        :data:`BAD_LENGTH` or :data:`BAD_CHECKSUM`. Pure: no state, no counters."""
        ...


@dataclass(frozen=True, slots=True)
class BinaryFraming:
    """A binary frame layout: ``sync``, header (``header_len`` bytes, sync included) from
    which ``payload_len`` reads the payload length (None: an impossible header), payload,
    then ``trailer_len`` check bytes that ``check`` verifies over the whole frame."""

    sync: bytes
    header_len: int
    trailer_len: int
    payload_len: Callable[[bytes], int | None]
    check: Callable[[bytes], bool]
    max_payload: int

    def measure(self, buf: bytes | bytearray, pos: int, max_payload: int) -> int:
        """See :meth:`Framing.measure`."""
        avail = len(buf) - pos
        for i in range(1, min(avail, len(self.sync))):
            if buf[pos + i] != self.sync[i]:
                return NOT_A_FRAME
        if avail < self.header_len:
            return NEED_MORE
        n_payload = self.payload_len(bytes(buf[pos : pos + self.header_len]))
        if n_payload is None or n_payload > max_payload:
            return BAD_LENGTH
        size = self.header_len + n_payload + self.trailer_len
        if avail < size:
            return NEED_MORE
        return size if self.check(bytes(buf[pos : pos + size])) else BAD_CHECKSUM


class Framed(Protocol):
    """What the framer reads of a registry entry (:class:`drivers.protocols.ProtocolSpec`)."""

    @property
    def name(self) -> str: ...

    @property
    def framing(self) -> Framing: ...


_PRINTABLE = rb"[\t\r\x20-\x7e]"


class Framer:
    """Finds the frames of ``protocols`` in an arbitrary byte stream; ``feed`` never blocks.

    ``feed(data)`` returns the frames completed by ``data``; a frame split across feeds is
    returned once complete. ``flush()`` (at end of stream) resolves bytes still held for an
    incomplete candidate, so frames hidden behind a false header are not lost.
    ``max_payload`` overrides a protocol's payload bound, by protocol name.
    """

    def __init__(
        self,
        protocols: Iterable[Framed],
        counters: Counters | None = None,
        *,
        max_payload: Mapping[str, int] | None = None,
        max_comment: int = DEFAULT_MAX_COMMENT,
    ) -> None:
        self.counters = counters if counters is not None else Counters()
        self.max_comment = max_comment
        self._log = RateLimitedLog(log)  # garbage fails a checksum at every sync byte
        protocols = list(protocols)
        self.max_payload: dict[str, int] = {p.name: p.framing.max_payload for p in protocols}
        for name, limit in (max_payload or {}).items():
            if name not in self.max_payload:
                raise ValueError(f"max_payload: no protocol {name!r}")
            self.max_payload[name] = limit
        # Candidates by first byte, longest sync first: protocols may share a first byte
        # (SBF ``$@`` and NMEA ``$``) as long as their sync patterns differ.
        self._by_first: dict[int, tuple[tuple[str, Framing, int], ...]] = {}
        syncs: dict[bytes, str] = {}
        for p in protocols:
            sync = bytes(p.framing.sync)
            if sync in syncs:
                raise ValueError(
                    f"protocols {syncs[sync]} and {p.name} have the same sync {sync!r}"
                )
            syncs[sync] = p.name
            entry = (p.name, p.framing, self.max_payload[p.name])
            cands = (*self._by_first.get(sync[0], ()), entry)
            self._by_first[sync[0]] = tuple(sorted(cands, key=lambda c: -len(c[1].sync)))
        firsts = b"".join(re.escape(bytes([b])) for b in self._by_first)
        self._first_re = re.compile(b"[" + firsts + b"]") if firsts else None
        self._buf = bytearray()
        self._offset = 0  # stream offset of self._buf[0]
        self._prev = 0x0A  # byte before self._buf[0]; stream start counts as a line start
        self._skipping = False
        self._comment_re = re.compile(rb"#" + _PRINTABLE + rb"*\n")
        self._comment_prefix_re = re.compile(rb"#" + _PRINTABLE + rb"*")

    @property
    def buffered(self) -> int:
        """Bytes held for an incomplete candidate frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; return the frames they complete, in stream order."""
        if data:
            self.counters["bytes_in"] += len(data)
            self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[Frame]:
        """End of stream: decide every held byte (incomplete candidates become garbage)."""
        frames = self._scan(final=True)
        if self._buf:  # cannot happen: final scans consume everything
            self._skip(len(self._buf))
            self._consume(len(self._buf))
        return frames

    # --- scanning ----------------------------------------------------------------------------
    def _scan(self, *, final: bool) -> list[Frame]:
        frames: list[Frame] = []
        buf = self._buf
        by_first = self._by_first
        pos = 0
        n = len(buf)
        while pos < n:
            b = buf[pos]
            cands = by_first.get(b)
            if cands is not None:
                if len(cands) == 1:  # the common case, inline
                    name, framing, limit = cands[0]
                    size = framing.measure(buf, pos, limit)
                    if size < 0 and size != NEED_MORE:
                        self._count_bad(name, framing, size, pos)
                        size = NOT_A_FRAME
                else:
                    name, size = self._measure(cands, buf, pos)
            elif b == 0x23 and (buf[pos - 1] if pos else self._prev) == 0x0A:  # '#' at BOL
                size = self._try_comment(pos)
                if size > 0:
                    self.counters["comment_lines"] += 1
                    self.counters["comment_bytes"] += size
                    self._skipping = False
                    pos += size
                    continue
            else:
                size = NOT_A_FRAME
            if size == NEED_MORE and not final:
                break
            if size > 0:
                frames.append(Frame(name, bytes(buf[pos : pos + size]), self._offset + pos))
                self.counters[f"frames_{name}"] += 1
                self._skipping = False
                pos += size
                continue
            # not a frame here (or an incomplete candidate at end of stream): skip one byte
            self._skip(1)
            pos += 1
        self._consume(pos)
        return frames

    def _measure(
        self, cands: tuple[tuple[str, Framing, int], ...], buf: bytearray, pos: int
    ) -> tuple[str, int]:
        """Of several candidates, the first (longest sync first) with a frame at ``pos``: its
        name and size; else NEED_MORE if any candidate waits for bytes, else NOT_A_FRAME. A bad
        length or checksum is counted for the candidate that found it, once the bytes are
        decided (not while another candidate waits for more)."""
        results = []
        for name, framing, limit in cands:
            size = framing.measure(buf, pos, limit)
            if size > 0:
                return name, size
            results.append((name, framing, size))
        if any(size == NEED_MORE for _, _, size in results):
            return results[0][0], NEED_MORE
        for name, framing, size in results:
            self._count_bad(name, framing, size, pos)
        return results[0][0], NOT_A_FRAME

    def _count_bad(self, name: str, framing: Framing, size: int, pos: int) -> None:
        if size == BAD_LENGTH:
            self.counters[f"bad_length_{name}"] += 1
        elif size == BAD_CHECKSUM:
            self.counters[f"bad_checksum_{name}"] += 1
            if isinstance(framing, BinaryFraming):  # not for text: noisy lines are common
                at = self._offset + pos
                self._log.debug(name, "%s checksum failure at stream offset %d", name, at)

    def _skip(self, count: int) -> None:
        if not self._skipping:
            self.counters["resyncs"] += 1
            self._skipping = True
        self.counters["bytes_skipped"] += count

    def _consume(self, count: int) -> None:
        if count:
            self._prev = self._buf[count - 1]
            del self._buf[:count]
            self._offset += count

    def _try_comment(self, pos: int) -> int:
        end = min(len(self._buf), pos + self.max_comment)
        window = bytes(self._buf[pos:end])
        m = self._comment_re.match(window)
        if m is None:
            p = self._comment_prefix_re.match(window)
            at_end = p is not None and p.end() == len(window) == len(self._buf) - pos
            if at_end and len(window) < self.max_comment:
                return NEED_MORE
            return NOT_A_FRAME
        line = window[: m.end()]
        # A valid frame that ends the line ends the comment before its first byte.
        if self._first_re is not None:
            for first in self._first_re.finditer(line, 1):
                start = first.start()
                for _, framing, limit in self._by_first[line[start]]:
                    if framing.measure(line, start, limit) == len(line) - start:
                        return start
        return m.end()


class WeekContext:
    """The GPS week for messages that carry only a time of week (RTCM MSM, UBX MEASX).

    Sources by rank, each replacing the reference unless a higher rank has set it:

    - ``HINT``: ``--gps-week`` (the constructor) or the system clock of a live stream
      (:meth:`set_hint`);
    - ``STREAM``: a week the stream gives with a time near now: a broadcast ephemeris's week
      and t_oe (RTCM 1019, 1042, 1044, 1045, 1046; SBF BDSNav, GPSNav, GALNav), a UBX
      NAV-PVT date (:meth:`set_approx`);
    - ``EXACT``: the receiver's own time tag (UBX RXM-RAWX, NAV-TIMEGPS; :meth:`set_exact`).

    A time of week is resolved to the week (of the reference week and its neighbours) that
    puts it nearest the last known time, which also carries the week across a rollover. A
    truncated broadcast week (GPS 10 bits) is resolved by :meth:`broadcast_week` against the
    reference, else the system clock (``clock_week``), else a sane epoch. When the stream's
    week replaces a hint more than a week away, that is logged (a wrong system clock or
    ``--gps-week``).

    Once the receiver's own time is known, a stream report is only compared with it: one more
    than DISAGREE_S away is counted in :attr:`disagreements` and logged as below, and
    :meth:`set_approx` returns False. Once the stream has given a week, a stream report more
    than DISAGREE_S from the reference
    (one damaged ephemeris message: a week field off by one moves every later epoch a week) is
    ignored: :meth:`set_approx` returns False, :attr:`disagreements` counts it, and it is
    logged (rate-limited, per source). The stream's new time is taken only when reports say
    it consistently: CONFIRM_IN_A_ROW in a row, each within DISAGREE_S of the one before,
    none agreeing with the reference in between, and the latest reports of more kinds of
    message (``source``) saying the new time than the reference (one system's messages can
    all be damaged alike, and come in bursts; a stream whose first report was the damaged one
    is corrected by the others); that is logged as a warning.
    """

    HINT, STREAM, EXACT = 0, 1, 2
    DISAGREE_S = 86_400.0
    """A stream report further than this from the reference [s] disagrees with it: an
    ephemeris's t_oe is within hours of its transmission (BDS hourly, ICD B1I 5.2.4.9; GPS
    and Galileo within their 4 h fit), a day leaves room for a stored set."""
    CONFIRM_IN_A_ROW = 3
    HANDOVER_S = 4 * 3600.0
    """How near a week boundary a set's t_oe and the stream's time must both be for the set's
    week, the week of its transmission, to be moved across it (:meth:`toe_week`): a GPS
    set's fit interval, within which it is broadcast around its t_oe."""

    def __init__(
        self,
        gps_week: int | None = None,
        *,
        clock_week: Callable[[], int | None] = system_clock_gps_week,
    ) -> None:
        self._ref: tuple[int, float | None] | None = None
        self._rank = -1
        self.source = ""
        """What set the reference (for the log and the tests)."""
        self.clock_week = clock_week
        self.disagreements = 0
        """Stream reports ignored for disagreeing with the reference."""
        # the latest stream report of each kind of message (source), and the run of
        # disagreeing reports in a row: (the latest, how many, each near the one before)
        self._latest: dict[str, tuple[int, float]] = {}
        self._run: tuple[tuple[int, float], int] | None = None
        self._log = RateLimitedLog(log)
        if gps_week is not None:
            self._ref, self._rank, self.source = (gps_week, None), self.HINT, "--gps-week"

    @property
    def known(self) -> bool:
        return self._ref is not None

    @property
    def exact(self) -> bool:
        return self._rank == self.EXACT

    def set_exact(self, gps_week: int, tow_s: float) -> None:
        self._set(self.EXACT, gps_week, tow_s, "receiver time")

    def set_approx(self, gps_week: int, tow_s: float, source: str = "stream") -> bool:
        """A week the stream gives (``source`` names its kind of message); False when it is
        ignored for disagreeing with the stream's week (see the class), or with the
        receiver's own time once that is known (never taken then: only compared, so that a
        damaged ephemeris week is counted whichever time the stream keeps)."""
        ref = self._ref
        if self._rank == self.EXACT and ref is not None and ref[1] is not None:
            if self._near((gps_week, tow_s), ref):
                return True
            return self._ignored(gps_week, tow_s, source, ref[0], ref[1])
        if self._rank == self.STREAM and not self._agrees(gps_week, tow_s, source):
            return False
        self._set(self.STREAM, gps_week, tow_s, source)
        self._latest[source] = (gps_week, tow_s)
        return True

    def _near(self, a: tuple[int, float], b: tuple[int, float | None]) -> bool:
        return b[1] is not None and abs(diff_s(a[0], a[1], b[0], b[1])) <= self.DISAGREE_S

    def _agrees(self, gps_week: int, tow_s: float, source: str) -> bool:
        """Whether a stream report may set the reference (see the class): it agrees with it,
        or it completes a run of reports that say the stream's new time, from more kinds of
        message than still say the reference's."""
        ref = self._ref
        report = (gps_week, tow_s)
        if ref is None or ref[1] is None or self._near(report, ref):
            self._run = None
            return True
        self._latest[source] = report
        if self._run is not None and self._near(report, self._run[0]):
            self._run = (report, self._run[1] + 1)
        else:
            self._run = (report, 1)
        saying_new = sorted(k for k, r in self._latest.items() if self._near(r, report))
        saying_ref = sorted(k for k, r in self._latest.items() if self._near(r, ref))
        ref_week, ref_tow = ref[0], float(ref[1])
        if self._run[1] >= self.CONFIRM_IN_A_ROW and len(saying_new) > len(saying_ref):
            log.warning(
                "GPS week %d (tow %.0f s) replaces week %d (tow %.0f s): %d reports in a row "
                "say so, the latest of %s (against %s)",
                gps_week,
                tow_s,
                ref_week,
                ref_tow,
                self._run[1],
                ", ".join(saying_new),
                ", ".join(saying_ref) or "none",
            )
            self._run = None
            return True
        return self._ignored(gps_week, tow_s, source, ref_week, ref_tow)

    def _ignored(
        self, gps_week: int, tow_s: float, source: str, ref_week: int, ref_tow: float
    ) -> bool:
        """A report that disagrees with the reference (``ref_week``, ``ref_tow``): counted,
        logged (rate-limited per ``source``); False."""
        self.disagreements += 1
        self._log.warning(
            source,
            "ignored GPS week %d tow %.0f s from %s: %.1f days from the stream's week %d tow "
            "%.0f s (a damaged message?)",
            gps_week,
            tow_s,
            source,
            diff_s(gps_week, tow_s, ref_week, ref_tow) / 86_400.0,
            ref_week,
            ref_tow,
        )
        return False

    def set_hint(self, gps_week: int, tow_s: float, source: str = "system clock") -> None:
        self._set(self.HINT, gps_week, tow_s, source)

    def _set(self, rank: int, gps_week: int, tow_s: float, source: str) -> None:
        if rank < self._rank:
            return
        week, tow = normalize(gps_week, tow_s)
        if self._rank < rank:
            if self._rank == self.HINT and self._ref is not None and abs(week - self._ref[0]) > 1:
                log.warning(
                    "GPS week %d from %s replaces week %d from %s",
                    week,
                    source,
                    self._ref[0],
                    self.source,
                )
            else:  # the first week, or one that confirms the hint: news, not trouble
                log.log(
                    logging.DEBUG if rank == self.HINT else logging.INFO,
                    "GPS week %d from %s",
                    week,
                    source,
                )
            self._rank, self.source = rank, source
        self._ref = (week, tow)

    def broadcast_week(self, week_mod: int, modulus: int, offset: int = 0) -> int:
        """The GPS week of a week broadcast modulo ``modulus`` and counted from GPS week
        ``offset`` (GPS/QZSS: 1024 and 0; Galileo: 4096 and 1024)."""
        ref = self._ref[0] if self._ref is not None else None
        if ref is None:
            ref = self.clock_week() or MIN_SANE_GPS_WEEK
        return offset + nearest_week(week_mod, modulus, ref - offset)

    def toe_week(self, week: int, toe_s: float) -> tuple[int, bool]:
        """The GPS week of a set's t_oe from the week its message gives, which is the week
        of transmission (GPS subframe 1's WN, IS-GPS-200 20.3.3.3.1.1, which RTCM 1019's
        DF076 carries; Galileo's WN, OS SIS ICD 5.1.2, in RTCM 1045/1046): a set broadcast in
        the last :data:`HANDOVER_S` of a week for a t_oe in the first of the next one (or the
        reverse) belongs to the next (previous) week, since t_oe is within half a week of its
        transmission (IS-GPS-200 20.3.4.5). Moved only when the stream's time (the reference)
        is in that week's last (first) hours and t_oe in the other's, so that a week field
        off by one elsewhere still disagrees; True when moved."""
        ref = self._ref
        if ref is None or ref[1] is None or week != ref[0]:
            return week, False
        end = WEEK_S - self.HANDOVER_S
        if toe_s < self.HANDOVER_S and ref[1] >= end:
            return week + 1, True
        if toe_s >= end and ref[1] < self.HANDOVER_S:
            return week - 1, True
        return week, False

    def resolve(self, tow_s: float) -> int | None:
        """GPS week of a GPST time of week, or None when no week is known yet."""
        if self._ref is None:
            return None
        ref_week, ref_tow = self._ref
        if ref_tow is None:
            week = ref_week
        else:
            week = min(
                (ref_week - 1, ref_week, ref_week + 1),
                key=lambda w: abs(diff_s(w, tow_s, ref_week, ref_tow)),
            )
        self._ref = (week, tow_s)
        return week
