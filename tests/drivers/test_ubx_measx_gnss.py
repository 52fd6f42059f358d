"""UBX RXM-MEASX of GPS L1 C/A (gnssId 0) and Galileo E1 (gnssId 2) beside BeiDou (issue 19),
on the gpsd project's real ZED-F9P capture, which has RXM-MEASX and RXM-RAWX every epoch.

The reference here is pyubx2's own parse of the same frames (independent of the mapper's
struct fast path): MEASX code phases against RAWX prMes of the same satellites and epoch.
"""

from __future__ import annotations

import collections
import functools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyubx2 import UBX_PROTOCOL, UBXReader
from pyubx2.ubxhelpers import calc_checksum

from drivers.framing import WeekContext
from drivers.source import StreamDecoder
from drivers.ubx import UbxMapper
from service.core.types import MeasurementEpoch
from service.sim.ubx import MeasxSv, measx_frame
from tests.support.paths import DATA

HPG = DATA / "ublox-logs" / "ublox-zed-f9p_hpg1.11.log"
C = 299_792_458.0
LSB_M = C * 2.0**-21 * 1e-3  # one codePhase step as a range: 0.143 m
PERIOD_MS = {0: 1, 2: 4, 3: 1}  # GPS L1 C/A, Galileo E1, BDS B1I code periods
LETTER = {0: "G", 2: "E", 3: "C"}


@functools.cache
def _messages(path: Path) -> tuple:
    with open(path, "rb") as stream:
        return tuple(
            (raw, msg)
            for raw, msg in UBXReader(stream, protfilter=UBX_PROTOCOL, quitonerror=0)
            if msg is not None and msg.identity in ("RXM-MEASX", "RXM-RAWX")
        )


def _blocks(msg, count: str) -> list[dict]:
    n = int(getattr(msg, count))
    names = ("gnssId", "svId", "sigId", "prMes", "prValid", "wholeChips", "fracChips")
    names += ("codePhase", "intCodePhase")
    return [
        {k: getattr(msg, f"{k}_{i:02d}") for k in names if hasattr(msg, f"{k}_{i:02d}")}
        for i in range(1, n + 1)
    ]


def _at_1023_chips_per_ms(b: dict) -> bool:
    """The block's chip count is codePhase at 1.023 Mchip/s (L1 C/A, E1), to 0.01 chip."""
    chips = b["wholeChips"] + b["fracChips"] / 1024.0
    return abs((chips - 1023.0 * b["codePhase"] + 511.5) % 1023.0 - 511.5) < 0.01


def pairs() -> list[dict]:
    """Per satellite and epoch with a valid L1 C/A / E1 / B1I prMes and a 1.023 (2.046 for
    B1I) Mchip/s MEASX block: both, with the RAWX rcvTow and the MEASX gpsTOW."""
    out = []
    measx = None
    for _raw, msg in _messages(HPG):
        if msg.identity == "RXM-MEASX":
            measx = msg
            continue
        if measx is None:
            continue
        code: dict[tuple[int, int], list[dict]] = collections.defaultdict(list)
        for b in _blocks(measx, "numSv"):
            if b["gnssId"] == 3 or (b["gnssId"] in (0, 2) and _at_1023_chips_per_ms(b)):
                code[(b["gnssId"], b["svId"])].append(b)
        for m in _blocks(msg, "numMeas"):
            key = (m["gnssId"], m["svId"])
            if m["gnssId"] in PERIOD_MS and m["sigId"] in (0, 1) and m["prValid"] and key in code:
                assert len(code[key]) == 1  # one block of this signal per satellite
                out.append(
                    dict(
                        gnss=m["gnssId"],
                        prn=f"{LETTER[m['gnssId']]}{m['svId']:02d}",
                        pr=m["prMes"],
                        rcv_tow_ms=round(msg.rcvTow * 1000.0),
                        gps_tow_ms=int(measx.gpsTOW),
                        int_ms=code[key][0]["intCodePhase"],
                        code_ms=code[key][0]["codePhase"],
                    )
                )
        measx = None
    return out


def offset_m(p: dict, tow_ms: int) -> float:
    """mod(prMes, c*T) - c*mod(tow_ms + intCodePhase + codePhase, T), wrapped to +-c*T/2."""
    t = PERIOD_MS[p["gnss"]]
    ct = C * t * 1e-3
    frac = C * (((tow_ms + p["int_ms"]) % t) + p["code_ms"]) * 1e-3
    return (p["pr"] % ct - frac + ct / 2) % ct - ct / 2


def test_measx_code_phase_is_prmes_modulo_the_code_period_for_each_system():
    """GPS (1 ms), Galileo E1 (4 ms) and BeiDou (1 ms): mod(prMes, c*T) minus the MEASX
    code phase is one constant per system, flat to one codePhase step, for every satellite.

    Measured: GPS 131.15 m, Galileo 129.13 m, BeiDou 129.15 m (a receiver-internal delay
    that prMes carries and the code phase does not, about 2 m apart between GPS and BDS:
    so the mapper calibrates each system on its own). For Galileo's 4 ms the whole ms of
    the code phase count from the receiver's RAWX rcvTow, not from MEASX's gpsTOW (whole
    seconds here, 1 or 2 ms after rcvTow as the receiver clock steps)."""
    ps = pairs()
    by = collections.Counter(p["gnss"] for p in ps)
    assert by == {0: 2750, 2: 2616, 3: 2663}  # every RAWX L1 C/A, E1 and B1I row with MEASX
    expected = {0: 131.15, 2: 129.13, 3: 129.15}
    for gnss, median_m in expected.items():
        d = np.array([offset_m(p, p["rcv_tow_ms"]) for p in ps if p["gnss"] == gnss])
        assert np.ptp(d) <= LSB_M + 1e-3, gnss
        assert abs(np.median(d) - median_m) < 0.05, (gnss, np.median(d))
        for prn in {p["prn"] for p in ps if p["gnss"] == gnss}:
            dp = [offset_m(p, p["rcv_tow_ms"]) for p in ps if p["prn"] == prn]
            assert abs(np.median(dp) - np.median(d)) <= LSB_M, prn
    # Galileo counted from gpsTOW instead: off by the whole ms between the two tags
    gal = [p for p in ps if p["gnss"] == 2]
    lag = collections.Counter(p["gps_tow_ms"] - p["rcv_tow_ms"] for p in gal)
    assert set(lag) == {1, 2}
    for p in gal:
        d = offset_m(p, p["gps_tow_ms"]) - offset_m(p, p["rcv_tow_ms"])
        k = p["gps_tow_ms"] - p["rcv_tow_ms"]
        assert abs(abs(d) - C * 1e-3 * min(k, 4 - k)) < 1e-3


def _decode(data: bytes, systems: str) -> tuple[list[MeasurementEpoch], StreamDecoder]:
    dec = StreamDecoder(mapper_options={"ubx": {"systems": frozenset(systems)}})
    events = dec.feed(data) + dec.flush()
    return [e for e in events if isinstance(e, MeasurementEpoch)], dec


def _withhold(n_of_epoch) -> tuple[bytes, dict[tuple[float, str], float]]:
    """Clear trkStat bit 0 (prValid) of the RAWX rows chosen by ``n_of_epoch(k, rows)`` in
    every epoch, re-sealing each frame: the capture's bytes and, per (rcvTow, satellite),
    the withheld prMes."""
    data = bytearray(HPG.read_bytes())
    withheld = {}
    for k, (raw, msg) in enumerate(m for m in _messages(HPG) if m[1].identity == "RXM-RAWX"):
        rows = _blocks(msg, "numMeas")
        edited = bytearray(raw)
        for i in n_of_epoch(k, rows):
            m = rows[i]
            edited[6 + 16 + 32 * i + 30] &= 0xFE
            withheld[(msg.rcvTow, f"{LETTER[m['gnssId']]}{m['svId']:02d}")] = m["prMes"]
        at = data.find(raw)
        data[at : at + len(raw)] = bytes(edited[:-2]) + calc_checksum(bytes(edited[2:-2]))
    return bytes(data), withheld


def _one_of_each(k: int, rows: list[dict]) -> list[int]:
    """One valid GPS L1 C/A and one valid Galileo E1 row, a different one each epoch."""
    chosen = []
    for gnss in (0, 2):
        idx = [
            i
            for i, m in enumerate(rows)
            if m["gnssId"] == gnss and m["sigId"] in (0, 1) and m["prValid"]
        ]
        chosen.append(idx[k % len(idx)])
    return chosen


def test_measx_fraction_recovers_withheld_gps_and_galileo_prmes():
    """Withhold one GPS and one Galileo prMes per epoch: each satellite comes out
    fractional (pr NaN) with its system's period, and its calibrated MEASX fraction equals
    the withheld mod(prMes, c*T) to within one codePhase step (0.143 m), the calibration
    taken from the system's other satellites."""
    data, withheld = _withhold(_one_of_each)
    epochs, dec = _decode(data, "CGE")
    assert len(epochs) == 654
    resid = collections.defaultdict(list)
    for ep in epochs:
        for (tow, prn), pr in withheld.items():
            if tow != ep.gpst_tow_s:
                continue
            i = ep.prn.index(prn)
            assert math.isnan(ep.pr_m[i]) and ep.signal[i] == "1C"
            t_s = {"G": 1e-3, "E": 4e-3}[prn[0]]
            assert ep.period_s[i] == t_s
            ct = C * t_s
            resid[prn[0]].append((ep.frac_pr_m[i] - pr % ct + ct / 2) % ct - ct / 2)
    assert {k: len(v) for k, v in resid.items()} == {"G": 654, "E": 654}
    for v in resid.values():
        assert np.max(np.abs(v)) < LSB_M + 5e-3
    assert dec.counters["measx_uncalibrated"] == 0


def test_full_rows_fraction_is_modulo_their_systems_period():
    epochs, _ = _decode(HPG.read_bytes(), "CGE")
    for ep in epochs:
        for i, prn in enumerate(ep.prn):
            t_s = 4e-3 if prn[0] == "E" else 1e-3
            assert ep.period_s[i] == t_s
            assert 0.0 <= ep.frac_pr_m[i] < C * t_s
            if np.isfinite(ep.pr_m[i]):
                assert ep.frac_pr_m[i] == ep.pr_m[i] % (C * t_s)


@pytest.mark.parametrize("systems", ["C", "CG", "CE", "CGE"])
def test_measx_rows_follow_the_systems_selection(systems):
    """Satellites only MEASX has come out fractional for the selected systems alone: the
    same set as pyubx2 finds (a 1.023 Mchip/s MEASX block and no valid RAWX prMes of that
    signal in the epoch)."""
    expected = collections.Counter()
    measx = None
    for _raw, msg in _messages(HPG):
        if msg.identity == "RXM-MEASX":
            measx = msg
            continue
        if measx is None:
            continue
        full = {
            (m["gnssId"], m["svId"])
            for m in _blocks(msg, "numMeas")
            if m["prValid"] and (m["gnssId"] == 3 or m["sigId"] in (0, 1))
        }
        for b in _blocks(measx, "numSv"):
            letter = LETTER.get(b["gnssId"])
            if letter is None or letter not in systems or (b["gnssId"], b["svId"]) in full:
                continue
            if (b["gnssId"] == 3 or _at_1023_chips_per_ms(b)) and b["intCodePhase"] != 255:
                expected[f"{letter}{b['svId']:02d}"] += 1
        measx = None
    epochs, dec = _decode(HPG.read_bytes(), systems)
    only = collections.Counter(
        p for ep in epochs for i, p in enumerate(ep.prn) if not np.isfinite(ep.pr_m[i])
    )
    assert only == expected
    assert {p[0] for ep in epochs for p in ep.prn} == set(systems)
    assert dec.counters["measx_only_sats"] == sum(expected.values())
    assert dec.counters["measx_uncalibrated"] == 0
    if "G" in systems:  # GPS MEASX-only satellites: G08, G13, G16, G21, G24, G29
        assert {p for p in only if p[0] == "G"} == {"G08", "G13", "G16", "G21", "G24", "G29"}
        # the L2C blocks of the four dual-band satellites, one per epoch each (1308 - 654)
        assert dec.counters["measx_G_other_signal"] > 0
    else:
        assert dec.counters["measx_G_other_signal"] == 0
    if "E" in systems:  # E5b blocks: counted, not read
        assert dec.counters["measx_E_other_signal"] == 2324


_ANY_BLOCK = st.tuples(
    st.sampled_from([0, 2, 3, 6]),  # GPS, Galileo, BeiDou, GLONASS
    st.integers(0, 255),  # svId
    st.integers(0, 65535),  # wholeChips (65535: invalid)
    st.integers(0, 1023),  # fracChips
    st.integers(0, 2**32 - 1),  # codePhase [2^-21 ms]
    st.integers(0, 255),  # intCodePhase (255: invalid)
)


@st.composite
def _l1_block(draw):
    """A GPS or Galileo block whose chips are its code phase at 1.023 Mchip/s."""
    code = draw(st.integers(0, 2**21 - 1))
    int_ms = draw(st.integers(0, 3))
    chips = code * 1023  # 2^-21 chip
    whole = (chips >> 21) + 1023 * int_ms
    return (
        draw(st.sampled_from([0, 2])),
        draw(st.integers(1, 36)),
        whole,
        (chips >> 11) & 1023,
        code,
        draw(st.sampled_from([int_ms, 255])),
    )


_BLOCK = st.one_of(_ANY_BLOCK, _l1_block())


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(_BLOCK, max_size=30), st.integers(0, 604_799_999))
def test_any_measx_frame_maps_to_rows_within_their_period(blocks, tow_ms):
    """Arbitrary MEASX blocks of every system (the fuzzers' mapper reads BeiDou alone):
    nothing raises, and every row is fractional modulo its own system's c*T."""
    svs = [
        MeasxSv(
            gnss_id=g,
            sv_id=sv,
            cn0_dbhz=30,
            whole_chips=whole,
            frac_chips=frac,
            code_phase_units=code,
            int_code_phase_ms=int_ms,
        )
        for g, sv, whole, frac, code, int_ms in blocks
    ]
    mapper = UbxMapper(week=WeekContext(2300), systems=frozenset("CGE"))
    events = mapper.on_frame(measx_frame(tow_ms, tow_ms, svs)) + mapper.flush()
    for ep in (e for e in events if isinstance(e, MeasurementEpoch)):
        for i, prn in enumerate(ep.prn):
            t_s = 4e-3 if prn[0] == "E" else 1e-3
            assert prn[0] in "CGE" and ep.period_s[i] == t_s
            assert math.isnan(ep.pr_m[i]) and 0.0 <= ep.frac_pr_m[i] < C * t_s
