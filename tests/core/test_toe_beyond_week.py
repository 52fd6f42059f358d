"""A GPS or Galileo t_oe outside the week is kept as read, never wrapped into a later week
(service.core.timebase.toe_gpst_to_bdt), so the ephemeris store refuses the set for what it
is (check ``time_of_week``) instead of holding a time made of the damage.

Real sets, each with its t_oe field damaged: the GPS LNAV subframes 1-3 of the PolyU F9P
capture (t_oe = 0xFFFF x 16 s, the field's largest value, IS-GPS-200 Table 20-III) and a GPS
record of the HKSC RINEX nav file (t_oe 700,000 s). The expected values are the ICD's
field scales and the file's own numbers, worked out by hand below.
"""

from __future__ import annotations

from pathlib import Path

from pyubx2 import UBXReader

from drivers.rinex import read_nav
from service.core import gps_nav as gn
from service.core.ephemeris import EphemerisStore, ephemeris_problem
from service.core.timebase import toe_gpst_to_bdt
from tests.support.paths import DATA

POLYU_UBX = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
HKSC_NAV = DATA / "hksc-2021" / "hksc1610.nav"
DATA_BITS = 240  # an LNAV subframe's data stream: ten words of 24 data bits
TOE_START, TOE_BITS = 216, 16  # subframe 2, Table 20-III: t_oe, 16 bits, scale 16 s
TOE_MAX_S = 0xFFFF * 16  # 1,048,560 s: beyond the week


def test_a_time_of_the_week_is_put_on_bdt_and_one_beyond_it_is_kept_as_read():
    # BDT = GPST - 14 s, BDT week = GPS week - 1356 (BDS-SIS-ICD 3.1.3)
    assert toe_gpst_to_bdt(2360, 100.0) == (1004, 86.0)
    assert toe_gpst_to_bdt(2360, 10.0) == (1003, 604796.0)  # the end of BDT's last week
    assert toe_gpst_to_bdt(2360, float(TOE_MAX_S)) == (1004, float(TOE_MAX_S))
    assert toe_gpst_to_bdt(2360, -16.0) == (1004, -16.0)


def _lnav_sets() -> dict[str, dict[int, int]]:
    """The capture's GPS L1 C/A subframes 1-3 (their data streams) by satellite, the last of
    each; the subframe ID read from the HOW here (bits 43-45 of the stream)."""
    out: dict[str, dict[int, int]] = {}
    with open(POLYU_UBX, "rb") as fh:
        for _, msg in UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is None or msg.identity != "RXM-SFRBX" or msg.gnssId != 0 or msg.sigId != 0:
                continue
            words = [getattr(msg, f"dwrd_{i:02d}") & ((1 << 30) - 1) for i in range(1, 11)]
            data = gn.subframe_data(words)
            sf_id = (data >> (DATA_BITS - 46)) & 0b111
            if sf_id in (1, 2, 3):
                out.setdefault(f"G{msg.svId:02d}", {})[sf_id] = data
    return {prn: sfs for prn, sfs in out.items() if len(sfs) == 3}


def _with_toe(sf2: int, raw: int) -> int:
    shift = DATA_BITS - TOE_START - TOE_BITS
    return (sf2 & ~(((1 << TOE_BITS) - 1) << shift)) | (raw << shift)


def test_an_lnav_toe_beyond_the_week_is_refused_as_such():
    sets = _lnav_sets()
    assert sets, "no complete GPS LNAV set in the capture"
    week = 2333  # GPS week of 2024-09-25
    for prn, sf in sets.items():
        good = gn.ephemeris_from_subframes(prn, sf[1], sf[2], sf[3], week)
        assert 0.0 <= good.toe_sow_s < 604800.0
        assert ephemeris_problem(good) is None, prn
        bad = gn.ephemeris_from_subframes(prn, sf[1], _with_toe(sf[2], 0xFFFF), sf[3], week)
        assert bad.toe_sow_s == TOE_MAX_S, prn  # as read, not 443,746 s of a later week
        problem = ephemeris_problem(bad)
        assert problem is not None and problem.check == "time_of_week", (prn, problem)


def test_a_rinex_gps_toe_beyond_the_week_is_refused_as_such(tmp_path: Path):
    text = HKSC_NAV.read_text()
    head = "G01 2021 06 10 02 00 00"
    start = text.index(head)
    lines = text[start:].splitlines(keepends=True)
    # broadcast orbit 3 (the record's fourth line) opens with t_oe: 352800 s (Thursday 02:00)
    assert lines[3].split()[0] == ".352800000000D+06"
    lines[3] = lines[3].replace(".352800000000D+06", ".700000000000D+06", 1)
    damaged = tmp_path / "hksc1610.nav"
    damaged.write_text(text[:start] + "".join(lines))

    before = read_nav(HKSC_NAV, systems=("G",)).ephemerides["G01"]
    after = read_nav(damaged, systems=("G",)).ephemerides["G01"]
    assert 352786.0 in [e.toe_sow_s for e in before]  # 352800 - 14 s on BDT
    assert 352786.0 not in [e.toe_sow_s for e in after]
    (odd,) = [e for e in after if e.toe_sow_s == 700000.0]  # as read
    assert odd.week == 2161 - 1356  # the record's GPS week (2021-06-10), on BDT's count
    store = EphemerisStore()
    assert not store.add(odd)
    assert store.refused_by_reason == {"time_of_week": 1}
