"""Rate-limited log lines for conditions that repeat every epoch or frame.

A warning raised per epoch at 10 Hz floods the journal with 36,000 lines an hour that say
one thing. :class:`RateLimitedLog` logs the first occurrence of a key at once, then at most
one line per ``interval_s`` (wall clock, monotonic); that line says how many occurrences it
stands for: ``... (N more since the last line)``. Counters still count every occurrence;
the log only says that something is happening.

Keys are whatever names the condition (a message kind, a satellite and a check); each key
keeps its own interval, so a new satellite or a new kind of fault is logged at once.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Hashable

LOG_INTERVAL_S = 60.0
"""Default interval between two lines of one key [s]."""
MAX_KEYS = 1024
"""Keys remembered at most; beyond, keys idle for an interval are forgotten."""


class RateLimitedLog:
    """Log through ``logger`` at most once per ``interval_s`` per key (see the module)."""

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = LOG_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self.clock = clock
        # key -> [time of its last line, occurrences held back since]
        self._state: dict[Hashable, list[float]] = {}

    def log(self, level: int, key: Hashable, msg: str, *args: object) -> bool:
        """Log ``msg % args`` at ``level`` unless ``key`` was logged less than an interval
        ago (then it is only counted); returns whether a line was written."""
        now = self.clock()
        state = self._state.get(key)
        if state is not None and now - state[0] < self.interval_s:
            state[1] += 1
            return False
        held = int(state[1]) if state is not None else 0
        if state is None and len(self._state) >= MAX_KEYS:
            self._forget_idle(now)
        self._state[key] = [now, 0]
        if held:
            msg += " (%d more since the last line)"
            args = (*args, held)
        self.logger.log(level, msg, *args)
        return True

    def debug(self, key: Hashable, msg: str, *args: object) -> bool:
        return self.log(logging.DEBUG, key, msg, *args)

    def info(self, key: Hashable, msg: str, *args: object) -> bool:
        return self.log(logging.INFO, key, msg, *args)

    def warning(self, key: Hashable, msg: str, *args: object) -> bool:
        return self.log(logging.WARNING, key, msg, *args)

    def error(self, key: Hashable, msg: str, *args: object) -> bool:
        return self.log(logging.ERROR, key, msg, *args)

    def _forget_idle(self, now: float) -> None:
        idle = [k for k, (t, _) in self._state.items() if now - t >= self.interval_s]
        for k in idle or list(self._state)[: len(self._state) // 2]:
            del self._state[k]
