"""Saves of the ephemeris store off the receiver loop.

The loop takes a :class:`~service.core.ephemeris.StoreSnapshot` (a tuple of references to
immutable sets: microseconds) and hands it to a :class:`StoreWriter`, whose thread encodes
and writes it with :func:`~service.core.ephemeris.write_store` (temp file, fsync, rename,
fsync of the directory). The loop never waits for the encoding or the disk; the writer is
the store file's only writer while it runs, and :meth:`StoreWriter.close` writes the last
snapshot before it returns (the shutdown save is synchronous).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from service.core.ephemeris import StoreSnapshot, write_store

log = logging.getLogger(__name__)


class StoreWriter:
    """A thread that writes the newest snapshot it is given to ``path``.

    A snapshot submitted while another is being written waits; one submitted while another
    waits replaces it (only the newest content matters). Counters: ``saves`` and
    ``save_errors``; ``failed`` says the latest write failed (the loop submits again at its
    next save time); ``last_write_s`` is how long the latest write took."""

    def __init__(
        self,
        path: Path,
        write: Callable[[Path, StoreSnapshot], None] = write_store,
    ) -> None:
        self.path = path
        self._write = write
        self._cond = threading.Condition()
        self._pending: StoreSnapshot | None = None
        self._busy = False
        self._closed = False
        self._thread: threading.Thread | None = None
        self.saves = 0
        self.save_errors = 0
        self.failed = False
        self.last_write_s = 0.0

    @property
    def closed(self) -> bool:
        return self._closed

    def submit(self, snapshot: StoreSnapshot) -> None:
        """Queue ``snapshot`` for writing and return at once."""
        with self._cond:
            if self._closed:
                raise RuntimeError("store writer closed")
            self._pending = snapshot
            self._cond.notify_all()
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="bdsfix-store", daemon=True)
                self._thread.start()

    def idle(self, timeout_s: float | None = None) -> bool:
        """Wait until nothing is pending or being written; False if ``timeout_s`` ran out."""
        with self._cond:
            return self._cond.wait_for(
                lambda: self._pending is None and not self._busy, timeout=timeout_s
            )

    def close(self, final: StoreSnapshot | None = None) -> None:
        """Write ``final`` (it replaces anything pending) and stop; returns once written."""
        with self._cond:
            if final is not None:
                self._pending = final
            self._closed = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join()  # it writes what is pending, then ends
        with self._cond:
            leftover, self._pending = self._pending, None
        if leftover is not None:  # no thread ran (or it had ended): write here
            self._save(leftover)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                snapshot, self._pending = self._pending, None
                if snapshot is None:
                    return  # closed, nothing left
                self._busy = True
            try:
                self._save(snapshot)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _save(self, snapshot: StoreSnapshot) -> None:
        t0 = time.perf_counter()
        try:
            self._write(self.path, snapshot)
        except Exception as exc:  # a bug must not kill the thread: log, retry at next save
            self.save_errors += 1
            self.failed = True
            if isinstance(exc, OSError):
                log.error("cannot save ephemeris store %s: %s", self.path, exc)
            else:
                log.exception("cannot save ephemeris store %s", self.path)
            return
        self.last_write_s = time.perf_counter() - t0
        self.saves += 1
        self.failed = False
        log.info(
            "ephemeris store saved: %d entries in %s (%.0f ms)",
            len(snapshot),
            self.path,
            1e3 * self.last_write_s,
        )
