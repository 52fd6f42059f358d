"""The SOW-decode rule: after a restart a satellite's time is known once words 1-2 of the
first subframe whose preamble arrives after bit sync have decoded (D2 0.12 s, D1 1.2 s into
it); the older ``subframe`` rule waits for that subframe's end (0.6 s, 6 s).

The expected instants are worked out by hand below from the ICD figures (300-bit subframes
of 30-bit words, D2 at 500 bps, D1 at 50 bps), not by the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core.constants import C_M_S
from service.core.sow_rule import D1_SOW_DECODED_S, D2_SOW_DECODED_S, time_known_after_s
from service.core.timebase import BDT_GPST_OFFSET_S, diff_s
from service.core.types import MeasurementEpoch
from service.engine.tracker import FrameSyncTracker, SubframeEmulator

WEEK = 2240
RESTART_BDT_S = 1000.05  # BDT second of week of the restart
RESTART_GPST_S = RESTART_BDT_S + BDT_GPST_OFFSET_S
SYNC_S = 0.2


def test_sow_is_words_one_and_two():
    # 2 words x 30 bits: 60 bits at 500 bps and at 50 bps
    assert pytest.approx(0.12) == D2_SOW_DECODED_S
    assert pytest.approx(1.2) == D1_SOW_DECODED_S
    assert time_known_after_s("D2", "subframe") == pytest.approx(0.6)
    assert time_known_after_s("D1", "subframe") == pytest.approx(6.0)
    with pytest.raises(ValueError):
        time_known_after_s("D1", "end")


# (prn, flight time [s], rule, seconds from the restart to the time being known)
# GEO C01, flight 0.125 s: the first synced bit left at 1000.05 + 0.2 - 0.125 = 1000.125,
# the next D2 preamble (multiple of 0.6 s) at 1000.2, seen at 1000.325; SOW known 0.12 s
# later (0.395 s after the restart), the subframe's end 0.6 s later (0.875 s).
# MEO C20, flight 0.075 s: first synced bit 1000.175, next D1 preamble (multiple of 6 s)
# at 1002, seen at 1002.075; SOW known at +1.2 s (3.225 s after the restart), the end at +6 s
# (8.025 s).
CASES = [
    ("C01", 0.125, "sow", 0.395),
    ("C01", 0.125, "subframe", 0.875),
    ("C20", 0.075, "sow", 3.225),
    ("C20", 0.075, "subframe", 8.025),
]


@pytest.mark.parametrize(("prn", "flight_s", "rule", "known_s"), CASES)
def test_emulated_restart_knows_the_time_when_the_rule_says(prn, flight_s, rule, known_s):
    emu = SubframeEmulator(WEEK, RESTART_GPST_S, {prn: SYNC_S}, rule=rule)
    week, tow = emu.full_at_tow_s(prn, flight_s * C_M_S)
    assert diff_s(week, tow, WEEK, RESTART_GPST_S) == pytest.approx(known_s, abs=1e-9)


@pytest.mark.parametrize("rule", ["sow", "subframe"])
def test_the_tracker_turns_a_satellite_full_at_that_instant(rule):
    """Epochs every 10 ms after the restart: C01 is fractional until the rule's instant and
    full from the first epoch at or after it; the fractional value is the range mod 1 ms."""
    known_s = {"sow": 0.395, "subframe": 0.875}[rule]
    pr_m = 0.125 * C_M_S
    emu = SubframeEmulator(WEEK, RESTART_GPST_S, {"C01": SYNC_S}, rule=rule)
    tracker = FrameSyncTracker()
    tracker.restart(WEEK, RESTART_GPST_S, emu)
    went_full = None
    for k in range(0, 120):
        t = k * 0.01
        ep = MeasurementEpoch.from_columns(WEEK, RESTART_GPST_S + t, ["C01"], ["2I"], [pr_m])
        view, events = tracker.on_epoch(ep)
        if np.isfinite(view.pr_m[0]):
            went_full = went_full if went_full is not None else t
            assert [e.event for e in events] in ([], ["full"])
        else:
            assert t < known_s - 1e-9
            assert view.frac_pr_m[0] == pytest.approx(pr_m % (C_M_S * 1e-3))
    assert went_full == pytest.approx(np.ceil(round(known_s / 0.01, 6)) * 0.01)
