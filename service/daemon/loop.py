"""The stream loop of ``bdsfix replay`` and ``bdsfix run``.

The main thread feeds events to the :class:`~service.engine.pipeline.Pipeline` and hands
results to the outputs, none of which may block. Where the events come from depends on the
source:

- a live receiver (serial device or pty, TCP; :attr:`drivers.source.BinarySource.live`) and
  a capture file replayed at full speed are read in the main thread itself
  (:attr:`Runner.live_inline`, :attr:`Runner.inline`): the bytes of an epoch are read,
  decoded, solved and published by one thread, with no hand-over between threads on the
  way (each costs a wake-up and an interpreter-lock transfer, up to the switch interval). A
  live read returns within :data:`drivers.transport.READ_TIMEOUT_S`, with or without bytes,
  so the loop's timers run between reads;
- any other source (a paced replay, standard input, the built-in scenario) has a reader
  thread that puts its events into a bounded queue, which the main thread takes from.

Between events the main thread keeps time for STATUS messages, the systemd watchdog and
periodic saves of the ephemeris store (it prunes the store and takes a snapshot; a
:class:`~service.daemon.store_writer.StoreWriter` thread encodes and writes it), and it
stops cleanly on request (SIGTERM) after saving the store. When it has caught up with its
source it also sends the TRACK records the outputs hold (:mod:`service.output.publish`)
and makes the garbage collector's passes (:func:`collect_when_idle`), which would
otherwise fall inside an epoch.

Network nav sources (NTRIP, :mod:`service.daemon.netnav`) each have a reader thread of their
own feeding the queue (their events are rare: ephemerides every few minutes; the loop takes
them when it has caught up with the receiver); their events are marked
:class:`~service.daemon.netnav.Networked` and only their ephemerides are used. Such a source
ending or failing (a caster that refuses the credentials) is logged in one line and the
daemon reads on: the receiver is the stream.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from service.core.counters import skipped_input
from service.core.errors import BdsfixError
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    ReceiverFix,
    TimeOffset,
)
from service.daemon.netnav import NetNavGate, Networked
from service.daemon.store_writer import StoreWriter
from service.engine.pipeline import EpochResult, Pipeline
from service.engine.tracker import TrackEvent

log = logging.getLogger(__name__)

_END = object()
SWITCH_INTERVAL_S = 0.0005
GC_SAFETY_THRESHOLD = 20_000
"""While the loop runs, the cyclic garbage collector's automatic trigger (young objects
allocated and not freed) is this high, and the loop collects when it has caught up with its
source (:func:`collect_when_idle`): a young-generation pass at an arbitrary allocation
took 0.1-0.2 ms and an intermediate one up to several ms on the 2-core machine, landing
inside an epoch's decoding, solve or NMEA as often as every fourth epoch. The automatic
trigger stays as a safety net for a loop that never catches up."""
TIMER_SLACK_S = 1.0
EPOCH_TIMES_ENV = "BDSFIX_EPOCH_TIMES"
"""When this environment variable names a file, the loop keeps five times of each epoch
(:func:`time.perf_counter`, ``CLOCK_MONOTONIC`` on Linux, the clock of every process) and
writes them there, one epoch a line, when it ends: the source's last read with bytes
(``read_at_s`` of a live source read inline, else NaN), solve start, solve end, GGA handed
to the live NMEA sinks (the outputs' ``gga_out_s``, NaN without them) and publish end. For
``bench/bench_latency.py``, which pairs them with its own write and arrival times."""


class Outputs(Protocol):
    """What the loop publishes to (see :mod:`service.output.publish`)."""

    def epoch(self, result: EpochResult) -> None: ...
    def track(self, event: TrackEvent) -> None: ...
    def status(self, counters: Mapping[str, int | float]) -> None: ...
    def reopen(self) -> None: ...
    def gone(self) -> bool: ...
    def close(self) -> None: ...


@dataclass
class Runner:
    """Runs one source through the pipeline into the outputs."""

    events: Iterable[Any]
    pipeline: Pipeline
    outputs: Outputs
    source_counters: Mapping[str, int] = field(default_factory=dict)
    status_interval_s: float = 10.0
    store_path: Path | None = None
    store_save_interval_s: float = 60.0
    watchdog: Callable[[], Any] | None = None
    watchdog_interval_s: float | None = None
    on_result: Callable[[EpochResult], None] | None = None
    silence_warn_s: float = 0.0  # warn while the source gives nothing recognisable; 0: never
    _recognised: tuple[int, float] = (0, 0.0)  # (frames + RINEX epochs, since when)
    _silence_warned_at: float = -math.inf
    queue_size: int = 4096
    inline: bool = False
    """Read the source in the loop's own thread, without the reader thread: for a regular
    file replayed as fast as possible, where the thread would only add hand-overs of the
    interpreter lock (several per epoch, ~10 % of the replay's time) and nothing waits on
    I/O. A paced source keeps its reader thread (the loop's timers run while it sleeps)."""
    live_inline: bool = True
    """Read a live source (``events`` with a true ``live`` and a ``ticks()`` iterator, as
    :class:`drivers.source.BinarySource` on a serial device or TCP) in the loop's own
    thread: an epoch then reaches the solver without a hand-over between threads. Its
    ``None`` ticks (a read done and its events out, or a read that timed out) are where
    the periodic work runs. False keeps the reader thread (for tests comparing the two)."""
    nav_sources: Sequence[tuple[str, Iterable[Any], Mapping[str, int]]] = ()
    """Network nav sources: (redacted name, events, counters) each."""
    nav_max_age_s: float = 7200.0
    _gate: NetNavGate | None = None
    _nav_heard: set[str] = field(default_factory=set)
    _stop: threading.Event = field(default_factory=threading.Event)
    _reopen: threading.Event = field(default_factory=threading.Event)
    _error: BaseException | None = None
    _store_dirty: bool = False
    _store_writer: StoreWriter | None = None
    _latency: LatencyStats = field(default_factory=lambda: LatencyStats())
    _epoch_times: list[tuple[float, ...]] | None = None
    _live: bool = False  # reading a live source inline (run)

    def request_stop(self) -> None:
        self._stop.set()

    def request_reopen(self) -> None:
        self._reopen.set()

    def counters(self) -> dict[str, int | float]:
        src = self._source_snapshot()
        out: dict[str, int | float] = {f"source_{k}": v for k, v in src.items()}
        out.update(self.pipeline.counters)
        out.update(self._latency.counters())
        ggto_ns = self.pipeline.ggto_ns()
        if ggto_ns is not None:
            out["ggto_ns"] = ggto_ns
        for i, (_name, _events, counters) in enumerate(self.nav_sources):
            prefix = "ntrip_" if i == 0 else f"ntrip{i + 1}_"
            # a copy first (one C call): the source's thread may add a key meanwhile
            out.update({f"{prefix}{k}": v for k, v in dict(counters).items()})
        if self._gate is not None:
            out.update(self._gate.counters)
        if self._store_writer is not None:
            out["store_saves"] = self._store_writer.saves
            out["store_save_errors"] = self._store_writer.save_errors
        return out

    def _reader(self, q: queue.Queue[Any]) -> None:
        try:
            for ev in self.events:
                while not self._stop.is_set():
                    try:
                        q.put(ev, timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
        except BaseException as exc:  # reported by the main thread
            self._error = exc
        finally:
            q.put(_END)

    @staticmethod
    def _queue_taker(q: queue.Queue[Any]) -> Callable[[], Any]:
        """The next event from the reader thread's queue; None after 0.2 s without one."""

        def take() -> Any:
            try:
                return q.get(timeout=0.2)
            except queue.Empty:
                return None

        return take

    def _inline_taker(self, events: Iterable[Any]) -> Callable[[], Any]:
        """The next event straight from the source (:attr:`inline`, :attr:`live_inline`;
        ``None`` for a live source's tick); ``_END`` at its end or failure (kept for
        :meth:`run` to raise, as the reader thread does)."""
        source = iter(events)

        def take() -> Any:
            try:
                return next(source)
            except StopIteration:
                return _END
            except Exception as exc:  # reported after the final save, as from the reader
                self._error = exc
                return _END

        return take

    def _nav_reader(self, name: str, events: Iterable[Any], q: queue.Queue[Any]) -> None:
        """A network nav source into the queue; its end or failure ends only this thread."""
        try:
            for ev in events:
                while not self._stop.is_set():
                    try:
                        q.put(Networked(ev, name), timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
            if not self._stop.is_set():
                log.warning("nav %s: the source ended; no more network ephemerides", name)
        except BdsfixError as exc:
            log.error("%s", exc)
        except Exception as exc:  # a bug or a library failure: say so, read on
            log.error("nav %s: stopped: %s: %s", name, type(exc).__name__, exc)

    def run(self) -> int:
        """Process until the source ends or a stop is requested; returns the epoch count."""
        self.pipeline.on_track = self.outputs.track
        # A live receiver's epoch stays in this thread from its read to its GGA; with a
        # reader thread (other sources), and whenever a network nav or an output's I/O
        # thread holds the interpreter lock as an epoch arrives, the interpreter's default
        # 5 ms switch interval is what a hand-over may wait.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        # What exists now (modules, tables, the ephemeris store) lives as long as the loop:
        # keep it out of the collector's full passes, which would otherwise walk it all and
        # stall an epoch by milliseconds (~4 ms for a daemon's start-up heap).
        gc.collect()
        gc.freeze()
        thresholds = gc.get_threshold()
        gc.set_threshold(max(GC_SAFETY_THRESHOLD, thresholds[0]), *thresholds[1:])
        times_path = os.environ.get(EPOCH_TIMES_ENV)
        self._epoch_times = [] if times_path else None
        q: queue.Queue[Any] = queue.Queue(maxsize=self.queue_size)
        live = self._live = self.live_inline and bool(getattr(self.events, "live", False))
        if live:
            take = self._inline_taker(self.events.ticks())  # type: ignore[attr-defined]
        elif self.inline:
            take = self._inline_taker(self.events)
        else:
            take = self._queue_taker(q)
            reader = threading.Thread(
                target=self._reader, args=(q,), name="bdsfix-reader", daemon=True
            )
            reader.start()
        if self.nav_sources:
            self._gate = NetNavGate(self.nav_max_age_s)
        for i, (name, events, _counters) in enumerate(self.nav_sources):
            threading.Thread(
                target=self._nav_reader,
                args=(name, events, q),
                name=f"bdsfix-nav-{i + 1}",
                daemon=True,
            ).start()
        # outputs that hold TRACK records until a fix has its GGA out
        # (service.output.publish) get them sent whenever nothing waits
        release_tracks = getattr(self.outputs, "release_tracks", None)
        now = time.monotonic()
        next_status = now + self.status_interval_s
        next_save = now + self.store_save_interval_s
        next_dog = now + (self.watchdog_interval_s or 1e18)
        n = 0
        try:
            while not self._stop.is_set():
                ev = take()
                if ev is _END:
                    break
                if ev is not None:
                    n += self._handle(ev)
                    if self.outputs.gone():
                        log.info("every output's reader has gone: stopping")
                        break
                if self._reopen.is_set():
                    self._reopen.clear()
                    log.info("reopening outputs")
                    self.outputs.reopen()
                # Caught up: nothing read waits to be handled (a live source's tick; the
                # queue empty). Periodic work waits for that gap between events (the
                # subframes that open an epoch's burst would otherwise delay its fix by a
                # store save), unless a backlog has kept it waiting for TIMER_SLACK_S
                # already. A save interval of 0 asks for a save after every change: no
                # waiting then.
                caught_up = (ev is None) if live else (self.inline or q.empty())
                if caught_up and (live or self.inline):
                    self._take_networked(q)
                if caught_up:
                    if release_tracks is not None:
                        release_tracks()
                    collect_when_idle(thresholds)
                now = time.monotonic()
                slack = 0.0 if caught_up else TIMER_SLACK_S
                if now >= next_status + slack:
                    self.outputs.status(self.counters())
                    next_status = now + self.status_interval_s
                if now >= next_save + (slack if self.store_save_interval_s > 0 else 0.0):
                    self.save_store()
                    next_save = now + self.store_save_interval_s
                if self.silence_warn_s > 0 and caught_up:  # seconds matter, not events
                    self._watch_silence(now)
                if self.watchdog is not None and now >= next_dog:
                    self.watchdog()
                    next_dog = now + (self.watchdog_interval_s or 1e18)
        finally:
            gc.set_threshold(*thresholds)
            gc.unfreeze()  # the caller's heap is its own again (tests run many loops)
            self._stop.set()
            self.save_store(final=True)
            self.outputs.status(self.counters())
            if times_path and self._epoch_times is not None:
                self._write_epoch_times(Path(times_path))
        if self._error is not None:
            raise self._error
        return n

    def _take_networked(self, q: queue.Queue[Any]) -> None:
        """Handle what the network nav threads queued (inline reading: nothing else is
        queued)."""
        while not q.empty():
            try:
                self._handle(q.get_nowait())
            except queue.Empty:
                return

    def _handle(self, ev: Any) -> int:
        if isinstance(ev, Networked):
            self._handle_networked(ev)
            return 0
        if isinstance(ev, MeasurementEpoch):
            if self._gate is not None:
                for eph in self._gate.on_epoch(ev.gpst_week, ev.gpst_tow_s):
                    self.pipeline.add_ephemeris(eph)
                    self._store_dirty = True
            t0 = time.perf_counter()
            result = self.pipeline.on_epoch(ev)
            t1 = time.perf_counter()
            self.outputs.epoch(result)
            t2 = time.perf_counter()
            self._latency.add(t0, t1, t2)
            if self._epoch_times is not None:
                self._epoch_times.append(
                    (
                        getattr(self.events, "read_at_s", math.nan) if self._live else math.nan,
                        t0,
                        t1,
                        getattr(self.outputs, "gga_out_s", math.nan),
                        t2,
                    )
                )
            if self.on_result is not None:
                self.on_result(result)
            return 1
        if isinstance(ev, NavSubframe):
            store = self.pipeline.store
            before = (len(store), store.dropped_inconsistent, store.dropped_unhealthy)
            self.pipeline.on_subframe(ev)
            # a decoded set that dropped the outside set it contradicts keeps the count
            after = (len(store), store.dropped_inconsistent, store.dropped_unhealthy)
            self._store_dirty |= after != before
        elif isinstance(ev, Ephemeris):
            self.pipeline.add_ephemeris(ev)
            self._store_dirty = True
        elif isinstance(ev, KlobucharParams):
            self.pipeline.set_iono(ev)
        elif isinstance(ev, ReceiverFix):
            self.pipeline.on_receiver_fix(ev)
        elif isinstance(ev, TimeOffset):
            self.pipeline.set_time_offset(ev)
        return 0

    def _write_epoch_times(self, path: Path) -> None:
        """The epochs' times (:data:`EPOCH_TIMES_ENV`) [s], one epoch a line."""
        try:
            with open(path, "w", encoding="ascii") as fh:
                for t in self._epoch_times or ():
                    fh.write(" ".join(f"{x:.9f}" for x in t) + "\n")
        except OSError as exc:
            log.warning("%s: epoch times not written: %s", path, exc.strerror)

    def _handle_networked(self, ev: Networked) -> None:
        """Ephemerides of a network source through the age gate; nothing else is used."""
        inner = ev.event
        if isinstance(inner, Ephemeris) and self._gate is not None:
            if ev.source not in self._nav_heard:
                self._nav_heard.add(ev.source)
                log.info("nav %s: receiving ephemerides", ev.source)
            for eph in self._gate.offer(inner, ev.source):
                self.pipeline.add_ephemeris(eph)
                self._store_dirty = True
        else:
            self.pipeline.counters["ntrip_ignored"] += 1

    def _watch_silence(self, now: float) -> None:
        """A live source that sends nothing recognisable (no frame, no RINEX epoch) for
        ``silence_warn_s`` gets a WARNING, repeated once per interval while it lasts
        (counted ``source_silent``); the daemon keeps reading."""
        c = self._source_snapshot()
        seen = sum(int(v) for k, v in c.items() if k.startswith("frames_")) + int(
            c.get("epochs_rinex", 0)
        )
        last, since = self._recognised
        if seen != last or since == 0.0:
            self._recognised = (seen, now)
            return
        if now - since >= self.silence_warn_s and now - self._silence_warned_at >= (
            self.silence_warn_s
        ):
            self._silence_warned_at = now
            self.pipeline.counters["source_silent"] += 1
            log.warning(
                "source: nothing recognisable for %.0f s (%d bytes received in all); "
                "check the receiver's output protocol and baud rate; still reading",
                now - since,
                int(c.get("bytes_in", 0)),
            )

    def _source_snapshot(self) -> dict[str, int]:
        """A copy of the source's counters: the reader thread adds keys while the loop reads
        them, and iterating a dict that grows raises. ``dict()`` of a dict copies it in one
        step under the GIL."""
        return dict(self.source_counters)

    def skipped(self) -> dict[str, int]:
        """Source counters of input that was dropped (bad bytes, frames, RINEX lines/epochs,
        phone rows: :func:`~service.core.counters.skipped_input`)."""
        return skipped_input(self._source_snapshot())

    def save_store(self, final: bool = False) -> None:
        """Save the ephemeris store if it changed (or the last write failed): prune it, take
        a snapshot and hand it to the writer thread; the loop's share is well under a
        millisecond for the bounded store. ``final`` (at shutdown) writes before returning
        and stops the writer."""
        if self.store_path is None:
            return
        writer = self._store_writer
        if writer is None or writer.closed:
            writer = self._store_writer = StoreWriter(self.store_path)
        snapshot = None
        if self._store_dirty or writer.failed:
            self.pipeline.prune_store()
            snapshot = self.pipeline.store.snapshot()
            self._store_dirty = False
        if final:
            writer.close(snapshot)
        elif snapshot is not None:
            writer.submit(snapshot)


def collect_when_idle(thresholds: tuple[int, ...]) -> None:
    """The collection the interpreter would have made by now under ``thresholds`` (its own,
    :func:`gc.get_threshold`), made here, where no event waits (:data:`GC_SAFETY_THRESHOLD`):
    a young pass once that many objects are pending, an intermediate one every
    ``thresholds[1]`` young passes, a full one every ``thresholds[2]`` intermediate ones
    (the start-up heap is frozen out of it, :meth:`Runner.run`)."""
    counts = gc.get_count()
    for generation in (2, 1, 0):
        if counts[generation] > thresholds[generation]:
            gc.collect(generation)
            return


class LatencyStats:
    """Time the receiver loop spends per epoch (solve + publish) and in publishing alone.

    Log-spaced histograms (5 % bins from 1 us), so the STATUS quantiles cost O(1) memory:
    ``epoch_loop_{p50,p99,max}_ms`` and ``epoch_publish_{p50,p99,max}_ms``.
    """

    _STEP = math.log(1.05)

    def __init__(self) -> None:
        self._hist: dict[str, Counter[int]] = {"loop": Counter(), "publish": Counter()}
        self._max: dict[str, float] = {"loop": 0.0, "publish": 0.0}

    def add(self, t_start: float, t_solved: float, t_published: float) -> None:
        for key, dt in (("loop", t_published - t_start), ("publish", t_published - t_solved)):
            self._hist[key][max(0, math.ceil(math.log(max(dt, 1e-6) / 1e-6) / self._STEP))] += 1
            self._max[key] = max(self._max[key], dt)

    def counters(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for key, hist in self._hist.items():
            n = sum(hist.values())
            if not n:
                continue
            for q in (0.5, 0.99):
                seen = 0
                for b in sorted(hist):
                    seen += hist[b]
                    if seen >= q * n:
                        out[f"epoch_{key}_p{round(q * 100)}_ms"] = round(
                            1e3 * min(1e-6 * math.exp(b * self._STEP), self._max[key]), 3
                        )
                        break
            out[f"epoch_{key}_max_ms"] = round(1e3 * self._max[key], 3)
        return out
