"""``nmea-file`` and ``jsonl``: NMEA sentences or JSON records as lines to a file or ``-``
(stdout). Files are truncated at open unless the options ask to append (the daemon does);
they are never opened through a symlink and are created 0644 whatever the umask
(:mod:`service.core.files`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Mapping
from typing import IO, Any

from service.core.counters import Counters
from service.core.errors import InputError
from service.core.files import open_output
from service.output.records import dumps
from service.output.sinks.base import Sink, SinkOptions

log = logging.getLogger(__name__)


def open_nmea_file(spec: str, options: SinkOptions) -> NmeaFileSink:
    return NmeaFileSink(spec, append=options.append)


def open_jsonl(spec: str, options: SinkOptions) -> JsonlSink:
    return JsonlSink(spec, append=options.append)


class LineSink(Sink):
    """Text lines to a file or ``-`` (stdout), line-buffered.

    :meth:`reopen` opens the path again in append mode, so after logrotate renamed the
    file, new lines go to a fresh file at the configured path. Write errors (disk full)
    are counted and logged once, never raised into the receiver loop.
    """

    def __init__(self, target: str, append: bool = False) -> None:
        self.target = target
        self._counters = Counters()
        self.reader_gone = False  # a pipe whose reader closed it (EPIPE)
        self._fh: IO[str] | None = None
        self._failing = False
        self._open(append)

    def counters(self) -> Mapping[str, int]:
        return dict(self._counters)

    def reopen(self) -> None:
        """Open the path again (SIGHUP); when that fails (a symlink planted there, a
        directory gone) the error is logged and counted and the old file stays in use."""
        try:
            self._open(append=True)
        except InputError as exc:
            self._counters["line_reopen_errors"] += 1
            log.error("%s; still writing to the file opened before", exc)

    def gone(self) -> bool:
        return self.reader_gone

    def _open(self, append: bool) -> None:
        if self.target == "-":
            self._fh = sys.stdout
            return
        old = self._fh
        self._fh = open_output(self.target, append=append, buffering=1)  # InputError
        if old is not None:
            with contextlib.suppress(OSError):
                old.close()
        self._failing = False

    def write(self, text: str) -> None:
        if self._fh is None or self.reader_gone:
            return
        try:
            self._fh.write(text)
        except BrokenPipeError:
            # a pipe (stdout, a FIFO) whose reader has left, as in `bdsfix replay | head`
            self.reader_gone = True
            self._counters["line_write_errors"] += 1
            log.info("%s: the reader closed the pipe; nothing more is written there", self.target)
            if self._fh is sys.stdout:  # no second EPIPE when Python flushes it at exit
                with contextlib.suppress(OSError, ValueError):
                    null = os.open(os.devnull, os.O_WRONLY)
                    os.dup2(null, sys.stdout.fileno())
                    os.close(null)
        except OSError as exc:
            self._counters["line_write_errors"] += 1
            if not self._failing:
                log.warning("cannot write %s: %s", self.target, exc.strerror)
            self._failing = True
        else:
            self._failing = False

    def close(self) -> None:
        if self._fh is not None and self._fh is not sys.stdout:
            with contextlib.suppress(OSError):
                self._fh.close()
        self._fh = None


class NmeaFileSink(LineSink):
    """Each epoch's NMEA sentences in one write, after the epoch's JSONL line."""

    nmea = "epoch"

    def write_nmea(self, data: bytes) -> None:
        self.write(data.decode("ascii"))


class JsonlSink(LineSink):
    """FIX and TRACK records, one compact JSON object a line."""

    records = frozenset({"FIX", "TRACK"})

    def write_record(self, cls: str, record: Mapping[str, Any]) -> None:
        self.write(dumps(record) + "\n")
