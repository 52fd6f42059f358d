"""RateLimitedLog: the first occurrence of a key at once, then one line per interval that
says how many occurrences it stands for (a fake clock: no timing)."""

from __future__ import annotations

import logging

from service.core.ratelog import MAX_KEYS, RateLimitedLog

LOGGER = logging.getLogger("tests.ratelog")


def test_first_line_at_once_then_one_per_interval_with_the_count(caplog):
    now = [0.0]
    rl = RateLimitedLog(LOGGER, 10.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="tests.ratelog"):
        written = []
        for k in range(100):  # 10 lines a second for 10 s
            now[0] = 0.1 * k
            written.append(rl.warning("offset", "offsets disagree by %.1f m", 40.0 + k))
        now[0] = 10.0
        written.append(rl.warning("offset", "offsets disagree by %.1f m", 1.0))
    assert written[0] and not any(written[1:100]) and written[100]
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "offsets disagree by 40.0 m",
        "offsets disagree by 1.0 m (99 more since the last line)",
    ]
    assert all(r.levelno == logging.WARNING for r in caplog.records)


def test_keys_are_limited_separately_and_levels_pass_through(caplog):
    now = [5.0]
    rl = RateLimitedLog(LOGGER, 60.0, clock=lambda: now[0])
    with caplog.at_level(logging.DEBUG, logger="tests.ratelog"):
        assert rl.info(("C08", "sqrt_a"), "a %s", 1)
        assert rl.error(("C08", "radius"), "b")
        assert rl.log(logging.DEBUG, ("C01", "sqrt_a"), "c")
        assert not rl.info(("C08", "sqrt_a"), "a %s", 2)
        now[0] = 70.0
        assert rl.info(("C08", "sqrt_a"), "a %s", 3)
        assert rl.info(("C08", "sqrt_a"), "a %s", 4) is False
        now[0] = 130.0
        assert rl.info(("C08", "sqrt_a"), "a %s", 5)
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "a 1"),
        (logging.ERROR, "b"),
        (logging.DEBUG, "c"),
        (logging.INFO, "a 3 (1 more since the last line)"),
        (logging.INFO, "a 5 (1 more since the last line)"),
    ]


def test_memory_is_bounded():
    now = [0.0]
    rl = RateLimitedLog(LOGGER, 1.0, clock=lambda: now[0])
    for k in range(3 * MAX_KEYS):
        now[0] = 0.001 * k
        rl.debug(k, "x")
    assert len(rl._state) <= MAX_KEYS
