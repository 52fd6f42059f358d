"""Android GnssLogger logs (drivers/gnsslogger.py) on the two shared phone logs.

The State table below is written from the Android ``GnssMeasurement`` reference (the
``STATE_*`` constants and ``getReceivedSvTimeNanos``' ranges per state), not from the
driver: every State value the two logs hold is listed with its bits by name and the period
the transmit time is known modulo for its system.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from drivers.gnsslogger import (
    GnssLoggerReader,
    events,
    known_period_s,
    nav_words,
    state_names,
)
from service.core.constants import C_M_S
from service.core.counters import Counters
from service.core.systems import GnssSystem, wavelength_m
from service.core.types import MeasurementEpoch, ReceiverFix
from tests.support.paths import DATA

PERTH = DATA / "android-perth-s8-2017" / "SensorLog20171005.txt"
BEIJING = DATA / "android-beijing-mi8-2022" / "gnss_log_2022_09_28_22_01_27.txt"

G, C, E, R = GnssSystem.GPS, GnssSystem.BDS, GnssSystem.GAL, GnssSystem.GLO
FULL = math.inf
# (system, State): (bit names, period [s] or FULL, None: no range). From the Android docs:
# CODE_LOCK 1, BIT_SYNC 2, SUBFRAME_SYNC 4, TOW_DECODED 8, MSEC_AMBIGUOUS 16, SYMBOL_SYNC 32,
# GLO_STRING_SYNC 64, GLO_TOD_DECODED 128, BDS_D2_BIT_SYNC 256, BDS_D2_SUBFRAME_SYNC 512,
# GAL_E1BC_CODE_LOCK 1024, GAL_E1C_2ND_CODE_LOCK 2048, GAL_E1B_PAGE_SYNC 4096, SBAS_SYNC
# 8192, TOW_KNOWN 16384, GLO_TOD_KNOWN 32768, 2ND_CODE_LOCK 65536. Ranges: code lock 1 ms
# (Galileo E1B/C 4 ms), BDS D2 bit sync 2 ms, bit sync 20 ms, E1C secondary code 100 ms,
# BDS D2 subframe 0.6 s, E1B page 2 s, subframe 6 s, TOW decoded/known: the week;
# MSEC_AMBIGUOUS: still ambiguous in the millisecond (taken as 1 ms). GLONASS and QZSS rows
# are not read (counted, skipped): their period is None here, their bits still checked.
STATES: dict[tuple[GnssSystem, int], tuple[tuple[str, ...], float | None]] = {
    # Perth, Galaxy S8
    (G, 4): (("SUBFRAME_SYNC",), None),
    (G, 5): (("CODE_LOCK", "SUBFRAME_SYNC"), 6.0),
    (G, 12): (("SUBFRAME_SYNC", "TOW_DECODED"), None),
    (G, 16): (("MSEC_AMBIGUOUS",), None),
    (G, 17): (("CODE_LOCK", "MSEC_AMBIGUOUS"), 1e-3),
    (G, 38): (("BIT_SYNC", "SUBFRAME_SYNC", "SYMBOL_SYNC"), None),
    (G, 39): (("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "SYMBOL_SYNC"), 6.0),
    (G, 46): (("BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC"), None),
    (G, 47): (("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC"), FULL),
    (G, 51): (("CODE_LOCK", "BIT_SYNC", "MSEC_AMBIGUOUS", "SYMBOL_SYNC"), 1e-3),
    (R, 16): (("MSEC_AMBIGUOUS",), None),
    (R, 17): (("CODE_LOCK", "MSEC_AMBIGUOUS"), None),
    (R, 49): (("CODE_LOCK", "MSEC_AMBIGUOUS", "SYMBOL_SYNC"), None),
    (R, 65): (("CODE_LOCK", "GLO_STRING_SYNC"), None),
    (R, 97): (("CODE_LOCK", "SYMBOL_SYNC", "GLO_STRING_SYNC"), None),
    (R, 99): (("CODE_LOCK", "BIT_SYNC", "SYMBOL_SYNC", "GLO_STRING_SYNC"), None),
    (R, 227): (
        ("CODE_LOCK", "BIT_SYNC", "SYMBOL_SYNC", "GLO_STRING_SYNC", "GLO_TOD_DECODED"),
        None,
    ),
    (C, 16): (("MSEC_AMBIGUOUS",), None),
    (C, 17): (("CODE_LOCK", "MSEC_AMBIGUOUS"), 1e-3),
    (C, 47): (("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC"), FULL),
    (C, 51): (("CODE_LOCK", "BIT_SYNC", "MSEC_AMBIGUOUS", "SYMBOL_SYNC"), 1e-3),
    (C, 521): (("CODE_LOCK", "TOW_DECODED", "BDS_D2_SUBFRAME_SYNC"), FULL),
    (E, 16): (("MSEC_AMBIGUOUS",), None),
    (E, 17): (("CODE_LOCK", "MSEC_AMBIGUOUS"), 1e-3),
    (E, 47): (("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC"), FULL),
    (E, 48): (("MSEC_AMBIGUOUS", "SYMBOL_SYNC"), None),
    (E, 50): (("BIT_SYNC", "MSEC_AMBIGUOUS", "SYMBOL_SYNC"), None),
    (E, 51): (("CODE_LOCK", "BIT_SYNC", "MSEC_AMBIGUOUS", "SYMBOL_SYNC"), 1e-3),
    (E, 1074): (("BIT_SYNC", "MSEC_AMBIGUOUS", "SYMBOL_SYNC", "GAL_E1BC_CODE_LOCK"), 1e-3),
    (E, 2080): (("SYMBOL_SYNC", "GAL_E1C_2ND_CODE_LOCK"), None),
    (E, 2082): (("BIT_SYNC", "SYMBOL_SYNC", "GAL_E1C_2ND_CODE_LOCK"), None),
    (E, 3106): (("BIT_SYNC", "SYMBOL_SYNC", "GAL_E1BC_CODE_LOCK", "GAL_E1C_2ND_CODE_LOCK"), 0.1),
    (E, 4138): (("BIT_SYNC", "TOW_DECODED", "SYMBOL_SYNC", "GAL_E1B_PAGE_SYNC"), None),
    (E, 5162): (
        ("BIT_SYNC", "TOW_DECODED", "SYMBOL_SYNC", "GAL_E1BC_CODE_LOCK", "GAL_E1B_PAGE_SYNC"),
        FULL,
    ),
    # Beijing, Mi 8 (GPS L1 and L5, QZSS L1 and L5, BDS B1I, Galileo E1)
    (G, 81929): (("CODE_LOCK", "TOW_DECODED", "TOW_KNOWN", "2ND_CODE_LOCK"), FULL),
    (GnssSystem.QZS, 47): (
        ("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC"),
        None,
    ),
    (GnssSystem.QZS, 81929): (("CODE_LOCK", "TOW_DECODED", "TOW_KNOWN", "2ND_CODE_LOCK"), None),
    (C, 65583): (
        ("CODE_LOCK", "BIT_SYNC", "SUBFRAME_SYNC", "TOW_DECODED", "SYMBOL_SYNC", "2ND_CODE_LOCK"),
        FULL,
    ),
    (C, 809): (
        ("CODE_LOCK", "TOW_DECODED", "SYMBOL_SYNC", "BDS_D2_BIT_SYNC", "BDS_D2_SUBFRAME_SYNC"),
        FULL,
    ),
    (E, 16392): (("TOW_DECODED", "TOW_KNOWN"), None),  # no code lock reported
}
"""Every (system, State) of the two logs, with what the Android docs say it means."""

MORE_STATES: dict[tuple[GnssSystem, int], float | None] = {
    (C, 1 | 256): 2e-3,  # BDS D2 bit sync
    (C, 1 | 2): 0.02,  # BDS D1 bit sync
    (C, 1 | 256 | 512): 0.6,  # BDS D2 subframe sync, TOW not yet decoded
    (C, 1 | 2 | 4): 6.0,  # BDS D1 subframe sync
    (G, 1 | 2): 0.02,
    (G, 1 | 16384): FULL,  # TOW known (not decoded)
    (E, 1024): 4e-3,  # E1B/C code lock
    (E, 1024 | 2048): 0.1,
    (E, 1024 | 4096): 2.0,
    (C, 1 | 8 | 16): 1e-3,  # TOW decoded but ms ambiguous: 1 ms
}
"""States the logs do not hold, for the periods they do not reach."""

_CONSTELLATION = {"1": G, "3": R, "4": GnssSystem.QZS, "5": C, "6": E}


def _states_in(path) -> set[tuple[GnssSystem, int]]:
    header: list[str] = []
    found = set()
    for line in path.open():
        if line.startswith("# Raw,"):
            header = line[2:].strip().split(",")
        elif line.startswith("Raw,"):
            f = line.strip().split(",")
            const = f[header.index("ConstellationType")]
            found.add((_CONSTELLATION[const], int(f[header.index("State")])))
    return found


@pytest.mark.parametrize("path", [PERTH, BEIJING], ids=["perth", "beijing"])
def test_every_state_in_the_logs_decodes_per_bit_as_android_defines_it(path):
    found = _states_in(path)
    assert found <= STATES.keys(), f"states not in the table: {sorted(found - STATES.keys())}"
    for key in sorted(found):
        names, period = STATES[key]
        assert set(state_names(key[1])) == set(names), key
        if key[0] in (G, C, E):
            assert known_period_s(key[0], key[1]) == period, key
        else:
            assert period is None


@pytest.mark.parametrize(("key", "period"), sorted(MORE_STATES.items()))
def test_periods_of_states_beyond_the_logs(key, period):
    assert known_period_s(*key) == period


def _epochs(path, counters=None) -> list[MeasurementEpoch]:
    return [e for e in events(path, counters) if isinstance(e, MeasurementEpoch)]


def test_perth_time_and_first_rows_from_the_clock_fields():
    """First Raw row: TimeNanos 2123000000, FullBiasNanos -1191199253693999999, BiasNanos
    0: GPST 1191199255816999999 ns = week 1969, 348055.816999999 s; BiasUncertaintyNanos
    5.968969500122643e9. Ten GPS at State 17: known modulo 1 ms."""
    counters = Counters()
    epochs = _epochs(PERTH, counters)
    first = epochs[0]
    assert first.gpst_week == 1969
    assert first.gpst_tow_s == pytest.approx(348055.816999999, abs=1e-6)
    assert first.time_unc_s == pytest.approx(5.968969500122643, rel=1e-12)
    assert first.prn == ("G02", "G03", "G05", "G06", "G07", "G09", "G16", "G23", "G28", "G30")
    assert np.isnan(first.pr_m).all()
    assert (first.period_s == 1e-3).all()
    # G02: ReceivedSvTimeNanos 19123676, receive time 348055816999999 ns: (rx - tx) mod 1 ms
    rx_ns, tx_ns = 348055816999999, 19123676
    assert first.frac_pr_m[0] == pytest.approx((rx_ns - tx_ns) % 10**6 * 1e-9 * C_M_S, abs=1e-6)
    # G02's PseudorangeRateMetersPerSecond 446.5701240515798 as a RINEX Doppler
    assert first.doppler_hz[0] == pytest.approx(-446.5701240515798 / wavelength_m("G02"))
    assert len(epochs) == counters["epochs_android"] == 445
    rows = counters["android_raw_rows"]
    used = counters["android_full"] + counters["android_fractional"]
    skipped = sum(
        counters[k]
        for k in (
            "android_other_gnss",
            "android_other_band",
            "android_no_code_lock",
            "android_sv_time_uncertain",
        )
    )
    assert rows == 10943 == used + skipped
    assert counters["android_other_gnss"] == 2099  # GLONASS


def test_perth_four_full_ranges_come_12_s_after_the_first_row():
    """As the data's README says: four satellites (nine GPS) have TOW decoded 12.0 s after
    the first Raw row; BeiDou C06 from 4 s (code lock), the GEOs from 83.6 s."""
    epochs = _epochs(PERTH)
    t0 = epochs[0].gpst_tow_s
    first4 = next(e for e in epochs if np.isfinite(e.pr_m).sum() >= 4)
    # the receive time tags: TimeNanos advanced 12 s, FullBias unchanged
    assert first4.gpst_tow_s - t0 == pytest.approx(12.0, abs=1e-6)
    full = {p for p, pr in zip(first4.prn, first4.pr_m, strict=True) if np.isfinite(pr)}
    assert full == {"G02", "G05", "G06", "G07", "G09", "G16", "G23", "G28", "G30"}
    first_bds = next(e for e in epochs if any(p.startswith("C") for p in e.prn))
    assert first_bds.gpst_tow_s - t0 == pytest.approx(4.0, abs=1e-6)
    first_geo = next(e for e in epochs if any(p in ("C01", "C02", "C04") for p in e.prn))
    assert 83.0 < first_geo.gpst_tow_s - t0 < 84.0


def test_perth_doppler_matches_the_pseudorange_change():
    """Physics: once the phone's time is fixed, the change of each full pseudorange over
    one epoch minus the range rate from Doppler (-lambda D) is the clock drift, common to
    all satellites: the spread about the median is a phone's code noise (a Doppler of the
    wrong sign would leave thousands of m/s)."""
    epochs = [e for e in _epochs(PERTH) if e.time_unc_s < 1e-6]
    spreads = []
    for a, b in itertools.pairwise(epochs):
        dt_s = b.gpst_tow_s - a.gpst_tow_s
        rows = []
        for i, prn in enumerate(a.prn):
            if prn in b.prn and np.isfinite(a.pr_m[i]):
                j = b.prn.index(prn)
                if np.isfinite(b.pr_m[j]):
                    rate = -wavelength_m(prn) * (a.doppler_hz[i] + b.doppler_hz[j]) / 2
                    rows.append((b.pr_m[j] - a.pr_m[i]) / dt_s - rate)
        if len(rows) >= 5:
            spreads.append(float(np.max(np.abs(np.asarray(rows) - np.median(rows)))))
    assert len(spreads) > 400
    assert np.median(spreads) < 15.0  # measured 9.8 m/s
    assert max(spreads) < 60.0  # measured 52 m/s


def test_perth_fractional_ranges_agree_with_the_full_range_that_follows():
    """A satellite fractional at one epoch and full at the next: the full range carried
    back one epoch by its Doppler and the clock drift (median over the satellites full at
    both) equals the fractional range modulo c times its period, within a phone's code
    noise (measured at most 7.5 m: C10, C01, C04 at 1 ms, four Galileo at 1 ms, G03 three
    times at 6 s)."""
    epochs = [e for e in _epochs(PERTH) if e.time_unc_s < 1e-6]
    checked = []
    for a, b in itertools.pairwise(epochs):
        dt_s = b.gpst_tow_s - a.gpst_tow_s
        both = [
            p
            for p in a.prn
            if p in b.prn
            and np.isfinite(a.pr_m[a.prn.index(p)])
            and np.isfinite(b.pr_m[b.prn.index(p)])
        ]
        drift = np.median(
            [
                (b.pr_m[b.prn.index(p)] - a.pr_m[a.prn.index(p)]) / dt_s
                + wavelength_m(p) * a.doppler_hz[a.prn.index(p)]
                for p in both
            ]
        )
        for i, prn in enumerate(a.prn):
            if prn not in b.prn or np.isfinite(a.pr_m[i]):
                continue
            j = b.prn.index(prn)
            if not np.isfinite(b.pr_m[j]):
                continue
            back = b.pr_m[j] - (-wavelength_m(prn) * a.doppler_hz[i] + drift) * dt_s
            ct = C_M_S * a.period_s[i]
            checked.append((prn, a.period_s[i], (back - a.frac_pr_m[i] + ct / 2) % ct - ct / 2))
    assert {p for p, _, _ in checked} >= {"C10", "C01", "C04", "G03"}
    assert {per for _, per, _ in checked} == {1e-3, 6.0}
    assert max(abs(r) for _, _, r in checked) < 20.0, checked


def test_beijing_is_read_whole_with_four_geos_full_at_d2_subframe_sync():
    counters = Counters()
    epochs = _epochs(BEIJING, counters)
    assert len(epochs) == 262
    assert counters["android_raw_rows"] == 11501
    used = counters["android_full"] + counters["android_fractional"]
    skipped = (
        counters["android_other_gnss"]  # GLONASS, QZSS
        + counters["android_other_band"]  # GPS L5
        + counters["android_no_code_lock"]  # Galileo at 16392
        + counters["android_sv_time_uncertain"]
    )
    assert used + skipped == 11501
    assert counters["android_other_band"] == 1048  # the GPS L5 rows (1176.45 MHz)
    assert counters["android_fractional"] == 0
    # the log stops inside its last epoch: 17 rows, none of them BeiDou
    assert not any(p.startswith("C") for p in epochs[-1].prn)
    for e in epochs[:-1]:
        geos = {p for p, pr in zip(e.prn, e.pr_m, strict=True) if np.isfinite(pr)}
        assert {"C01", "C02", "C04", "C05"} <= geos
        # GEO ranges: 35,786 km altitude seen from mid-latitudes, 37,000-40,500 km
        for p in ("C01", "C02", "C04", "C05"):
            assert 37.0e6 < e.pr_m[e.prn.index(p)] < 40.5e6
        assert set(e.signal) == {"2I", "1C"}


def _lines(path, n: int) -> list[str]:
    out = []
    for line in path.open():
        out.append(line)
        if len(out) >= n:
            break
    return out


def test_a_clock_discontinuity_is_a_restart_and_fix_rows_are_receiver_fixes():
    """HardwareClockDiscontinuityCount going from 0 to 1 (real rows of the Beijing log, the
    count edited) marks the epoch ``restarted``; a Fix row (GnssLogger's own layout)
    becomes a ReceiverFix on GPST (UTC + 18 s in 2022)."""
    head = _lines(BEIJING, 200)
    header = next(x for x in head if x.startswith("# Raw,"))[2:].strip().split(",")
    k = header.index("HardwareClockDiscontinuityCount")
    t = header.index("TimeNanos")
    raws = [x for x in head if x.startswith("Raw,")]
    times = sorted({int(x.split(",")[t]) for x in raws})
    edited = []
    for x in raws:
        f = x.split(",")
        if int(f[t]) >= times[2]:
            f[k] = "1"
        edited.append(",".join(f))
    fix = "Fix,GPS,39.9,116.3,50.0,0.0,3.5,1664373706000\n"
    lines = [x for x in head if x.startswith("#")] + edited[:40] + [fix] + edited[40:]
    counters = Counters()
    out = list(GnssLoggerReader(lines, counters))
    epochs = [e for e in out if isinstance(e, MeasurementEpoch)]
    assert [e.restarted for e in epochs[:4]] == [False, False, True, False]
    assert counters["android_clock_restarts"] == 1
    (rf,) = [e for e in out if isinstance(e, ReceiverFix)]
    assert rf.source == "android-gps"
    # 2022-09-28 14:01:46 UTC = GPST week 2229, Wednesday: 3 * 86400 + 14 h 1 min 46 s + 18 s
    assert rf.gpst_week == 2229
    assert rf.gpst_tow_s == pytest.approx(3 * 86400 + 14 * 3600 + 60 + 46 + 18)
    assert (rf.lat_deg, rf.lon_deg, rf.alt_m, rf.accuracy_m) == (39.9, 116.3, 50.0, 3.5)


def test_perth_gps_nav_rows_hold_subframes_in_the_android_layout():
    """The Perth log's 499 GPS L1 C/A Nav rows (type 0x0101, not decoded) read with the
    layout of ``GnssNavigationMessage.getData()`` (:func:`nav_words`): word 1 starts with
    the TLM preamble 10001011, and the subframe ID of the HOW (bits 20-22, IS-GPS-200
    20.3.3.2; bits 1-24 of a word are sent inverted when the previous word's D30 is 1) is
    the row's Sub-messageId."""
    counters = Counters()
    list(events(PERTH, counters))
    assert counters["android_nav_0x0101"] == 499
    assert counters["android_nav_0x0301"] == 742  # GLONASS strings
    assert counters["android_nav_bds"] == 0
    checked, placeholders = 0, []
    for line in PERTH.open():
        f = line.strip().split(",")
        if f[0] != "Nav" or f[2] != "257":
            continue
        words = nav_words(bytes(int(b) & 0xFF for b in f[6:]))
        assert words[0] >> 22 == 0b10001011
        if words[1] == 0x0BADC0DE:
            placeholders.append(f[1])
            continue
        assert (words[1] >> 8) & 0b111 == int(f[5])
        checked += 1
    assert checked == 498 and placeholders == ["3"]


def _android_nav_row(sub) -> str:
    """A Nav row holding a received B1I subframe as Android writes it: type 0x0501 (D1) or
    0x0502 (D2), status 1 (parity passed), each word in the last 30 bits of 4 bytes, big
    endian, as signed decimals."""
    kind = 0x0501 if sub.nav_type == "D1" else 0x0502
    data = b"".join(w.to_bytes(4, "big") for w in sub.words)
    signed = ",".join(str(b - 256 if b > 127 else b) for b in data)
    return f"Nav,{int(sub.prn[1:])},{kind},1,-1,{sub.fra_id},{signed}\n"


def test_bds_nav_rows_become_the_receivers_own_subframes():
    """Real B1I subframes (the Leuven SBF capture's BDSRaw: D1; its GEO's D2 are not on
    B1I) written as Android Nav rows among real Raw rows come back as the same NavSubframes
    (words, FraID, SOW, page), tagged with the receive time of the Raw epoch being read."""
    from drivers.source import open_source
    from service.core.types import NavSubframe

    with open_source(str(DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf")) as src:
        subs = [e for e in src if isinstance(e, NavSubframe)]
    assert {s.nav_type for s in subs} == {"D1"} and len(subs) >= 20
    head = _lines(BEIJING, 60)
    raws = [i for i, x in enumerate(head) if x.startswith("Raw,")]
    lines = head[: raws[3]] + [_android_nav_row(s) for s in subs] + head[raws[3] :]
    counters = Counters()
    out = list(GnssLoggerReader(lines, counters))
    got = [e for e in out if isinstance(e, NavSubframe)]
    assert counters["android_nav_bds"] == len(subs) == len(got)
    first = next(e for e in out if isinstance(e, MeasurementEpoch))
    for a, b in zip(got, subs, strict=True):
        assert (a.prn, a.nav_type, a.words, a.fra_id, a.sow_s, a.page) == (
            b.prn,
            b.nav_type,
            b.words,
            b.fra_id,
            b.sow_s,
            b.page,
        )
        assert (a.gpst_week, a.gpst_tow_s) == (first.gpst_week, first.gpst_tow_s)


def test_a_log_needs_nav_unless_it_holds_bds_nav_rows(tmp_path):
    from drivers.gnsslogger import needs_nav
    from drivers.source import open_source
    from service.core.types import NavSubframe

    assert needs_nav(BEIJING) and needs_nav(PERTH)  # Perth: GPS and GLONASS Nav rows only
    with open_source(str(DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf")) as src:
        sub = next(e for e in src if isinstance(e, NavSubframe))
    path = tmp_path / "with-bds-nav.txt"
    path.write_text("".join(_lines(BEIJING, 60)) + _android_nav_row(sub))
    assert not needs_nav(path)


def test_a_blank_time_uncertainty_is_unknown_and_an_impossible_svid_is_no_row():
    """Real Perth rows edited: BiasUncertaintyNanos left blank (the phone does not say how
    well it knows its time) gives ``time_unc_s`` inf, not an exact time, so the pipeline
    keeps the fractional ranges out of the fast fix; a Svid outside the system's PRNs (GPS
    99) gives no row and is counted."""
    head = _lines(PERTH, 400)
    header = next(x for x in head if x.startswith("# Raw,"))[2:].strip().split(",")
    u, sv, t = (header.index(k) for k in ("BiasUncertaintyNanos", "Svid", "TimeNanos"))
    raws = [x.split(",") for x in head if x.startswith("Raw,")]
    first_t = raws[0][t]
    rows = [f for f in raws if f[t] == first_t]
    for f in rows:
        f[u] = ""
    rows[0][sv] = "99"  # the first row is a GPS satellite at State 17 (docstring above)
    lines = [x for x in head if x.startswith("#")] + [",".join(f) for f in rows]
    counters = Counters()
    (epoch,) = [e for e in GnssLoggerReader(lines, counters) if isinstance(e, MeasurementEpoch)]
    assert epoch.time_unc_s == math.inf
    assert counters["android_bad_svid"] == 1
    assert len(epoch) == len(rows) - 1 and "G99" not in epoch.prn


# ------------------------------------------- damaged copies of the Perth log: clock and rows

HEAD_LINES = 4000
"""The Perth log's first 4000 lines: 3,472 Raw rows (2,701 of them kept: BeiDou, GPS, Galileo
with a usable range), 150 epochs (about 150 s)."""


def _perth_head() -> tuple[list[str], dict[str, int]]:
    """The first lines of the Perth log and its Raw columns by name (the first of a name)."""
    head = _lines(PERTH, HEAD_LINES)
    header = next(x for x in head if x.startswith("# Raw,"))[2:].strip().split(",")
    col: dict[str, int] = {}
    for i, name in enumerate(header):
        col.setdefault(name, i)
    return head, col


def _edit(head: list[str], col: dict[str, int], name: str, value: str, which=None) -> list[str]:
    """``head`` with the field ``name`` of the Raw rows numbered in ``which`` (from 1; None:
    every one) set to ``value``."""
    out, k = [], 0
    for line in head:
        if line.startswith("Raw,"):
            k += 1
            if which is None or k in which:
                f = line.rstrip("\n").split(",")
                f[col[name]] = value
                line = ",".join(f) + "\n"
        out.append(line)
    return out


def _first_rows(head: list[str], col: dict[str, int]) -> list[int]:
    """The numbers (from 1) of the Raw rows that open an epoch: a new TimeNanos."""
    out, k, last = [], 0, None
    for line in head:
        if line.startswith("Raw,"):
            k += 1
            t = line.split(",")[col["TimeNanos"]]
            if t != last:
                out.append(k)
            last = t
    return out


def _read(lines: list[str]) -> tuple[list[MeasurementEpoch], Counters]:
    counters = Counters()
    epochs = [e for e in GnssLoggerReader(lines, counters) if isinstance(e, MeasurementEpoch)]
    return epochs, counters


def _assert_same_epoch(a: MeasurementEpoch, b: MeasurementEpoch) -> None:
    assert (a.gpst_week, a.gpst_tow_s, a.prn, a.signal) == (
        b.gpst_week,
        b.gpst_tow_s,
        b.prn,
        b.signal,
    )
    assert (a.time_unc_s, a.restarted) == (b.time_unc_s, b.restarted)
    for name in ("pr_m", "frac_pr_m", "period_s", "cn0_dbhz", "doppler_hz"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


DAMAGED_CLOCKS = {
    # BiasNanos NaN on Raw rows 1001-1029 (the reviewer's gl_biasnan_mid.txt): once crashed
    # the JSON output after 75 fixes
    "bias_nan_mid": ("BiasNanos", "NaN", set(range(1001, 1030))),
    "bias_nan": ("BiasNanos", "NaN", None),
    "bias_inf": ("BiasNanos", "Infinity", None),
    # GPST = TimeNanos - FullBiasNanos: 1e30 ns is week 1.7e12; -2**63 + 1 week 15250 (2262)
    "full_bias_1e30": ("FullBiasNanos", "-1e30", None),
    "full_bias_min": ("FullBiasNanos", "-9223372036854775807", None),
    "full_bias_0": ("FullBiasNanos", "0", None),  # GPST 2.1 s: week 0
    "full_bias_positive": ("FullBiasNanos", "1191199253693999999", None),  # before 1980
}


@pytest.mark.parametrize("name", DAMAGED_CLOCKS)
def test_an_epoch_whose_clock_gives_no_time_is_skipped_and_counted(name):
    """The epoch's time is that of its first Raw row's clock fields (TimeNanos,
    FullBiasNanos, BiasNanos): an epoch whose first row's BiasNanos is not finite, or whose
    GPST is not a week of 2016-2058, is skipped and counted ``android_bad_time``; every
    other epoch is the undamaged log's, row for row (a damaged row later in an epoch takes
    the first row's clock, as the undamaged one does)."""
    head, col = _perth_head()
    field, value, which = DAMAGED_CLOCKS[name]
    clean, _ = _read(head)
    assert len(clean) == len(_first_rows(head, col)) == 150
    epochs, counters = _read(_edit(head, col, field, value, which))
    damaged = [
        k for k, first in enumerate(_first_rows(head, col)) if which is None or first in which
    ]
    assert counters["android_bad_time"] == len(damaged) and damaged
    kept = [e for k, e in enumerate(clean) if k not in damaged]
    assert len(epochs) == len(kept)
    for a, b in zip(epochs, kept, strict=True):
        _assert_same_epoch(a, b)


def test_a_repeated_row_is_one_measurement_the_first():
    """Every Raw row written twice (the reviewer's gl_dup_rows.txt; solved as independent
    measurements they had doubled the redundancy and shrunk HPL 53 -> 22 m) reads as the
    undamaged log; and when the repeat carries another ReceivedSvTimeNanos (+1 us: 300 m),
    the first row is the measurement. The repeats are counted ``android_duplicate_rows``,
    one per row the undamaged log gives."""
    head, col = _perth_head()
    clean, clean_counters = _read(head)
    shifted = {}
    for line in head:
        if line.startswith("Raw,"):
            f = line.rstrip("\n").split(",")
            f[col["ReceivedSvTimeNanos"]] = str(int(f[col["ReceivedSvTimeNanos"]]) + 1000)
            shifted[line] = ",".join(f) + "\n"
    for repeat in (lambda x: x, shifted.__getitem__):
        lines = [y for x in head for y in ((x, repeat(x)) if x.startswith("Raw,") else (x,))]
        epochs, counters = _read(lines)
        assert counters["android_duplicate_rows"] == sum(len(e) for e in clean) > 2500
        for key in ("android_full", "android_fractional"):
            assert counters[key] == clean_counters[key]
        assert len(epochs) == len(clean)
        for a, b in zip(epochs, clean, strict=True):
            _assert_same_epoch(a, b)


def test_a_time_that_never_advances_gives_one_bounded_epoch():
    """Every Raw row with the first row's TimeNanos (the reviewer's gl_timenanos_neg.txt:
    once one epoch of 3,472 rows on which the coarse-time fix's exclusion ran for minutes):
    one epoch that reads the first MAX_EPOCH_ROWS rows, the rest counted
    ``android_excess_rows``, each satellite once, the first epoch's satellites with the
    undamaged log's first measurements."""
    from drivers.gnsslogger import MAX_EPOCH_ROWS

    head, col = _perth_head()
    clean, _ = _read(head)
    n_raw = sum(x.startswith("Raw,") for x in head)
    first_time = next(x for x in head if x.startswith("Raw,")).split(",")[col["TimeNanos"]]
    (epoch,), counters = _read(_edit(head, col, "TimeNanos", first_time))
    assert n_raw > MAX_EPOCH_ROWS
    assert counters["android_excess_rows"] == n_raw - MAX_EPOCH_ROWS
    assert len(set(zip(epoch.prn, epoch.signal, strict=True))) == len(epoch) < 100
    assert counters["android_duplicate_rows"] > 500
    idx = [epoch.prn.index(p) for p in clean[0].prn]
    _assert_same_epoch(epoch.rows(idx), clean[0])
