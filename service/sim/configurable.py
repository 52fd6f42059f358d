"""The virtual receiver on a pty as a configurable u-blox receiver (``bdsfix simulate --pty
--wait-config``): it reads what the host writes, answers CFG messages
(:class:`service.sim.cfg.CfgResponder`) and sends only what it was asked for.

It starts as a receiver fresh from its defaults: BeiDou B1I on, GEOs not used, no UBX
measurement message on its port, so it says nothing until configured. Its scenario clock
runs from power-on (the process start); a signal configuration written to RAM (CFG-GNSS,
CFG-SIGNAL-*) restarts tracking, as on a real receiver: the scenario starts again at that
instant, at the true time of that instant, and the satellites are acquired, bit-synced and
decoded anew. The measurement period set by CFG-RATE decimates the simulator's own epochs;
the subframes completed in between go out with the next output epoch.

The pty is in raw mode and the master is non-blocking: like a UART, bytes written while
nobody reads the other end are lost once the tty's buffer is full (counted as
``dropped_bytes``), never blocking the receiver.
"""

from __future__ import annotations

import logging
import os
import queue
import select
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from pyubx2 import ERR_IGNORE, SETPOLL, UBX_PROTOCOL, UBXReader

from service.core.bds import is_geo
from service.sim.cfg import CfgResponder
from service.sim.simulator import SimEpoch, SimSubframe, Simulator, epoch_subset

log = logging.getLogger(__name__)


class _FdStream:
    """A blocking ``read(n)`` over a non-blocking descriptor, for pyubx2's reader; returns
    ``b""`` once ``stop`` is set or the descriptor is gone."""

    def __init__(self, fd: int, stop: threading.Event) -> None:
        self.fd = fd
        self.stop = stop

    def read(self, n: int = 1) -> bytes:
        buf = b""
        while len(buf) < n and not self.stop.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], 0.1)
                if not ready:
                    continue
                chunk = os.read(self.fd, n - len(buf))
            except BlockingIOError:
                continue
            except (OSError, ValueError):
                return b""
            if not chunk:
                return b""
            buf += chunk
        return buf if len(buf) == n else b""


@dataclass
class ServeStats:
    """What a configurable run did: epochs made and sent, bytes written and lost, restarts."""

    epochs_made: int = 0
    epochs_sent: int = 0
    bytes_written: int = 0
    dropped_bytes: int = 0
    restarts: int = 0
    answered: int = 0


class ConfigurableReceiver:
    """Serve ``make_sim(offset_s)`` (a simulator started ``offset_s`` after the first) on
    the master ``fd`` of a pty, answering CFG messages read from it with ``responder``."""

    def __init__(
        self,
        fd: int,
        make_sim: Callable[[float], Simulator],
        responder: CfgResponder,
        *,
        base_period_ms: int,
    ) -> None:
        self.fd = fd
        self.make_sim = make_sim
        self.responder = responder
        self.base_period_ms = base_period_ms
        self.stats = ServeStats()
        self._inbox: queue.Queue[object] = queue.Queue()
        self._stop = threading.Event()
        self._halt = threading.Event()
        os.set_blocking(fd, False)

    def stop(self) -> None:
        """End :meth:`serve` at the next epoch (from another thread)."""
        self._halt.set()

    def _read_host(self) -> None:
        reader = UBXReader(
            _FdStream(self.fd, self._stop),
            msgmode=SETPOLL,
            protfilter=UBX_PROTOCOL,
            quitonerror=ERR_IGNORE,
        )
        while not self._stop.is_set():
            try:
                _, msg = reader.read()
            except Exception as exc:  # a message pyubx2 cannot take: the host's problem
                log.debug("unreadable message from the host: %s", exc)
                continue
            if msg is not None:
                self._inbox.put(msg)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                self.stats.dropped_bytes += len(view)
                return
            self.stats.bytes_written += n
            view = view[n:]

    def _answer_until(self, due: float) -> bool:
        """Answer the host until ``due`` (monotonic); True if tracking must restart."""
        while True:
            wait = due - time.monotonic()
            try:
                msg = self._inbox.get(timeout=wait) if wait > 0 else self._inbox.get_nowait()
            except queue.Empty:
                return False
            reply = self.responder.handle(msg)
            if reply:
                self.stats.answered += 1
                self._write(reply)
            if self.responder.restart:
                self.responder.restart = False
                return True

    def serve(self) -> ServeStats:
        """Run until the scenario (since its last restart) ends."""
        reader = threading.Thread(target=self._read_host, name="sim-host-reader", daemon=True)
        reader.start()
        power_on = time.monotonic()
        try:
            while self._run_scenario(power_on):
                self.stats.restarts += 1
        finally:
            self._stop.set()
            reader.join(timeout=1.0)
        return self.stats

    def _tracked(self, prn: str) -> bool:
        """Whether the receiver, as configured, tracks ``prn`` (BDS on; a GEO if used)."""
        return self.responder.bds_on and (self.responder.use_geo or not is_geo(prn))

    def _run_scenario(self, power_on: float) -> bool:
        """One scenario from now to its end (False) or to a restart (True)."""
        t0 = time.monotonic()
        sim = self.make_sim(t0 - power_on)
        held: list[SimSubframe] = []  # completed in epochs not output (decimation)
        epochs: Iterator[SimEpoch] = sim.epochs()
        for ep in epochs:
            if self._halt.is_set():
                return False
            if self._answer_until(t0 + ep.t_s):
                return True
            self.stats.epochs_made += 1
            held.extend(ep.subframes)
            period = self.responder.meas_period_ms
            if round(ep.t_s * 1000.0) % period:
                continue
            outputs = self.responder.outputs
            if not outputs:
                held.clear()
                continue
            shown = epoch_subset(ep, self._tracked, subframes=held)
            held = []
            self._write(sim.encode(shown, outputs))
            self.stats.epochs_sent += 1
        return False
