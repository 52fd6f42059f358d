"""``nmea-serial``: NMEA 0183 to a serial device or pty (``/dev/ttyUSB1``), at the shared baud.

A writer thread owns the port; the caller only queues bytes, and whole payloads that would
overflow the bounded queue are dropped and counted, so a stalled port never blocks the
caller nor receives half a sentence.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import deque
from collections.abc import Mapping

import serial

from service.core.counters import Counters
from service.core.errors import InputError
from service.output.sinks.base import Sink, SinkOptions

log = logging.getLogger(__name__)


def open_sink(spec: str, options: SinkOptions) -> SerialSink:
    return SerialSink(spec, options.baud)


class SerialSink(Sink):
    """NMEA to a serial device or pty through a writer thread and a bounded queue.

    ``write_nmea`` never blocks: a payload that does not fit in ``max_pending_bytes`` is dropped
    whole (``nmea_serial_dropped``), so the port only ever carries complete sentences.
    A port that fails (device unplugged) is counted and logged; later payloads are dropped.
    """

    nmea = "live"

    def __init__(self, device: str, baud: int = 115200, max_pending_bytes: int = 16 * 1024):
        self.device = device
        self.max_pending_bytes = max_pending_bytes
        self._counters = Counters()
        try:
            self._port = serial.Serial(device, baud, write_timeout=None)
        except (serial.SerialException, OSError) as exc:
            raise InputError(f"NMEA serial {device}: {exc}") from exc
        self._cond = threading.Condition()
        self._queue: deque[bytes] = deque()
        self._pending = 0
        self._closed = False
        self._failed = False
        self._thread = threading.Thread(target=self._writer, name="bdsfix-nmea-serial", daemon=True)
        self._thread.start()

    def counters(self) -> Mapping[str, int]:
        return self._counters.snapshot()

    @property
    def pending_bytes(self) -> int:
        with self._cond:
            return self._pending

    def write_nmea(self, data: bytes) -> None:
        with self._cond:
            if self._closed or self._failed or self._pending + len(data) > self.max_pending_bytes:
                self._counters.add("nmea_serial_dropped")
                return
            self._queue.append(data)
            self._pending += len(data)
            self._cond.notify()

    def _writer(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                chunk = self._queue[0]
            try:
                self._port.write(chunk)  # blocks this thread only; close() cancels it
            except (serial.SerialException, OSError) as exc:
                with self._cond:
                    if self._closed:
                        return
                    self._failed = True
                    self._queue.clear()
                    self._pending = 0
                self._counters.add("nmea_serial_errors")
                log.warning("NMEA serial %s failed: %s", self.device, exc)
                return
            with self._cond:
                if self._queue and self._queue[0] is chunk:
                    self._queue.popleft()
                    self._pending -= len(chunk)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        with contextlib.suppress(Exception):
            self._port.cancel_write()
        self._thread.join(timeout=2)
        with contextlib.suppress(Exception):
            self._port.close()
