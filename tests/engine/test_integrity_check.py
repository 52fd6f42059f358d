"""The check of a fast fix's recovered ranges once each satellite's time of week decodes
(service.engine.recovered.RecoveredLedger, as the pipeline keeps it), on the TST urban
drive's u-blox receiver, whose clock steps by whole milliseconds (every range jumps by 300
km or more at once).

The truth is the file itself: every range the emulated restart made fractional is full in
the file, so a recovered range must equal the file's own range at the epoch it was recovered,
and its check must pass, however the receiver clock moved before the check.
"""

from __future__ import annotations

import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.constants import C_M_S
from service.engine.pipeline import Pipeline
from service.engine.recovered import RECOVERED_MAX_AGE_S
from tests.support.paths import DATA

TST = DATA / "hk-tst-urban-2019"


@pytest.fixture(scope="module")
def drive():
    store, iono = load_navigation([str(TST / "hksc1180.19b")])
    return store, iono, list(RinexObsReader(TST / "COM3_190428_124409.obs"))


def test_a_receiver_clock_step_between_recovery_and_check_is_no_failure(drive):
    """Restart at 178 s (seed 3): C14 is recovered at 46052.997 s and its SOW decodes at
    46060.003 s, after the receiver's clock stepped 6 ms (1799 km)."""
    store, iono, epochs = drive
    pipe = Pipeline(store, iono, restart_at_s=178.0, sync_seed=3)
    file_pr = {}
    checks = []
    t0 = epochs[0].gpst_tow_s
    for ep in epochs:
        if ep.gpst_tow_s - t0 > 230.0:
            break
        file_pr[round(ep.gpst_tow_s, 3)] = dict(zip(ep.prn, ep.pr_m.tolist(), strict=True))
        checks += pipe.on_epoch(ep).integrity
    assert len(checks) >= 3
    for c in checks:
        recovered_at = round(c.gpst_tow_s - c.elapsed_s, 3)
        assert c.recovered_pr_m == pytest.approx(file_pr[recovered_at][c.prn], abs=1.0)
        assert c.full_pr_m == file_pr[round(c.gpst_tow_s, 3)][c.prn]
        assert c.ok
    steps = [c for c in checks if abs(c.clock_change_m) > 0.9e-3 * C_M_S]
    assert steps, "the restart was chosen before a clock step: a check must span it"
    # what the check took out is the file's own jump, to the satellite's range change
    for c in steps:
        jump_m = c.full_pr_m - c.recovered_pr_m
        assert abs(jump_m - c.clock_change_m) < 1e3 * c.elapsed_s
    assert pipe.counters["integrity_failures"] == 0


def test_a_satellite_back_after_minutes_is_left_unchecked_not_failed(drive):
    """A satellite recovered by a fast fix, then not in the epochs for 200 s and back full:
    its range has moved by more than the check can tell from a wrong integer, so it is
    counted ``integrity_unchecked`` instead of being compared."""
    store, iono, epochs = drive
    pipe = Pipeline(store, iono, restart_at_s=60.0, sync_seed=3)
    t0 = epochs[0].gpst_tow_s
    victim = gone_at = None
    checked: list[str] = []
    for ep in epochs:
        t = ep.gpst_tow_s - t0
        if victim is not None and t < gone_at + 200.0:
            ep = ep.rows([i for i, p in enumerate(ep.prn) if p != victim])
        result = pipe.on_epoch(ep)
        checked += [c.prn for c in result.integrity]
        if victim is None and t > 60.0 and result.fix.mode == "fast":
            victim = next((p for p in result.fix.ambiguity if p in ("C11", "C12", "C14")), None)
            gone_at = t
        if gone_at is not None and t > gone_at + 200.0 + RECOVERED_MAX_AGE_S:
            break
    assert victim is not None
    assert victim not in checked
    assert pipe.counters["integrity_unchecked"] == 1
    assert pipe.counters["integrity_failures"] == 0


def _perth():
    from drivers.source import file_epochs
    from service.core.types import MeasurementEpoch

    perth = DATA / "android-perth-s8-2017"
    store, iono = load_navigation(
        [str(perth / "PERT00AUS_R_20172780000_01D_MN.rnx")], systems="CGE"
    )
    events, _ = file_epochs(perth / "SensorLog20171005.txt", systems=("C", "G", "E"))
    return store, iono, [e for e in events if isinstance(e, MeasurementEpoch)]


@pytest.mark.parametrize("wrong", [False, True])
def test_relative_integers_of_a_coarse_time_fix_are_checked_too(wrong):
    """The Perth phone's start (Galaxy S8, no SOW before 12 s, its time 6 s off): its first
    12 fixes are coarse-time fixes whose whole period common to each system's ranges is in
    doubt (``relative_ambiguity``). Once a system's satellites are full, the first of them
    gives that common shift and every other one must share it: 9 such checks, all passing
    (before, these fixes' integers were never checked). With one of the last coarse-time
    fix's GPS ranges made one period (1 ms) longer, a wrong integer, the GPS checks fail:
    its own, or, were it the first full one (the anchor of the shift), the others'."""
    store, iono, epochs = _perth()
    pipe = Pipeline(store, iono)
    relative = []
    checks = []
    for ep in epochs:
        result = pipe.on_epoch(ep)
        checks += result.integrity
        if result.fix.relative_ambiguity:
            relative.append(result.fix)
            if wrong and len(relative) == 12:  # one GPS integer one period off
                gps = [p for p in sorted(result.fix.relative_ambiguity) if p[0] == "G"]
                prn = min(gps, key=lambda p: pipe._ledger.recovered[p].period_s)
                pipe._ledger.recovered[prn].pr_m += C_M_S * pipe._ledger.recovered[prn].period_s
    assert len(relative) == 12
    assert pipe.counters["integrity_relative_anchors"] >= 2  # GPS and BeiDou
    from_relative = [c for c in checks if c.elapsed_s < 10 and c.gpst_tow_s < 348080]
    assert len(from_relative) >= 9
    failed = [c for c in checks if not c.ok]
    if wrong:  # (the range made wrong, or, if it was the first full, the others with it)
        assert failed and {c.prn[0] for c in failed} == {"G"}
        assert pipe.counters["integrity_failures"] == len(failed)
    else:
        assert not failed and pipe.counters["integrity_failures"] == 0
