"""The struct fast path for RXM-RAWX / MEASX / SFRBX against pyubx2, an independent decoder.

Every RAWX, MEASX and SFRBX frame of every real capture is unpacked both ways and every field the
fast path exposes must equal pyubx2's attribute of the same name. Frames the simulator
writes with :func:`service.sim.ubx.rawx_frame` / :func:`service.sim.ubx.measx_frame` are parsed by
pyubx2 and must carry the values put in (hypothesis over the field ranges).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyubx2 import UBXReader

from drivers.ubx import UbxMapper, _measx_rows, _sfrbx_fields, parse_rxm
from service.core.types import MeasurementEpoch
from service.sim.ubx import MeasxSv, RawxMeas, measx_frame, rawx_frame
from tests.support.paths import DATA

CAPTURES = sorted(
    [*DATA.glob("tiny-ubx-rtcm/*.log"), *DATA.glob("ublox-logs/*.log"), *DATA.glob("*/*.ubx")]
)


def _rxm_frames(path: Path) -> list[bytes]:
    with open(path, "rb") as stream:
        return [
            raw
            for raw, _ in UBXReader(stream, protfilter=2, quitonerror=0)
            if raw[2] == 0x02 and raw[3] in (0x13, 0x14, 0x15)
        ]


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return math.isclose(float(a), float(b), rel_tol=0.0, abs_tol=1e-12) or (  # type: ignore[arg-type]
            math.isnan(float(a)) and math.isnan(float(b))  # type: ignore[arg-type]
        )
    return a == b


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_fast_path_equals_pyubx2_on_real_captures(path: Path):
    frames = _rxm_frames(path)
    checked = 0
    for raw in frames:
        fast = parse_rxm(raw)
        ref = UBXReader.parse(raw)
        assert fast is not None and fast.identity == ref.identity
        for name, value in fast.fields().items():
            assert _same(value, getattr(ref, name)), (path.name, ref.identity, name)
            assert _same(getattr(fast, name), value)  # pyubx2's flat names read the same
            checked += 1
    if frames:
        assert checked > 0


def _epoch_key(ev: object) -> object:
    if not isinstance(ev, MeasurementEpoch):
        return ev
    cols = (ev.pr_m, ev.frac_pr_m, ev.period_s, ev.cn0_dbhz, ev.doppler_hz, ev.lock_s)
    return (ev.gpst_week, ev.gpst_tow_s, ev.prn, ev.signal, ev.source, *map(repr, map(list, cols)))


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_mapper_reads_frames_as_it_reads_pyubx2_messages(path: Path):
    """The mapper's own reading of RAWX and MEASX frames (``on_frame``: straight from their
    struct tuples) gives the epochs, subframes and counters that pyubx2's RAWX messages and
    :func:`parse_rxm`'s MEASX messages give it (pyubx2 scales MEASX's code phase with other
    float rounding, ~1e-8 m, which would hide nothing but fail bitwise: its MEASX fields are
    compared with those rows in ``test_measx_rows_equal_pyubx2_on_real_captures``). SFRBX
    frames (``on_frame``: :func:`_sfrbx_fields`) give what pyubx2's SFRBX messages give,
    with every system's subframes read."""
    systems = frozenset({"C", "G", "E"})
    fast, ref = UbxMapper(systems=systems), UbxMapper(systems=systems)
    got, want = [], []
    for raw in _rxm_frames(path):
        got += fast.on_frame(raw)
        want += ref.on_message(UBXReader.parse(raw) if raw[3] != 0x14 else parse_rxm(raw))
    got += fast.flush()
    want += ref.flush()
    assert [_epoch_key(e) for e in got] == [_epoch_key(e) for e in want]
    assert fast.counters == ref.counters


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_measx_rows_equal_pyubx2_on_real_captures(path: Path):
    """The MEASX rows the mapper reads (gpsTOW and per satellite gnssId, svId, cNo,
    dopplerHz, wholeChips, fracChips, codePhase, intCodePhase) are pyubx2's fields."""
    names = (
        "gnssId", "svId", "cNo", "dopplerHz", "wholeChips", "fracChips", "codePhase",
        "intCodePhase",
    )  # fmt: skip
    checked = 0
    for raw in _rxm_frames(path):
        if raw[3] != 0x14:
            continue
        got = _measx_rows(raw)
        ref = UBXReader.parse(raw)
        assert got is not None
        tow_ms, rows = got
        assert tow_ms == ref.gpsTOW and len(rows) == ref.numSv
        for i, row in enumerate(rows, start=1):
            for name, value in zip(names, row, strict=True):
                assert _same(value, getattr(ref, f"{name}_{i:02d}")), (path.name, i, name)
                checked += 1
    if any(raw[3] == 0x14 for raw in _rxm_frames(path)):
        assert checked > 0


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_sfrbx_fields_equal_pyubx2_on_real_captures(path: Path):
    """The SFRBX fields the mapper reads (gnssId, svId, sigId and the numWords data words)
    are pyubx2's."""
    checked = 0
    for raw in _rxm_frames(path):
        if raw[3] != 0x13:
            continue
        got = _sfrbx_fields(raw)
        ref = UBXReader.parse(raw)
        assert got is not None
        gnss_id, sv_id, sig_id, dwords = got
        assert (gnss_id, sv_id, sig_id) == (ref.gnssId, ref.svId, ref.sigId)
        assert dwords == tuple(getattr(ref, f"dwrd_{i:02d}") for i in range(1, ref.numWords + 1))
        checked += 1
    if any(raw[3] == 0x13 for raw in _rxm_frames(path)):
        assert checked > 0


def test_real_captures_hold_both_messages():
    kinds = {raw[3] for p in CAPTURES for raw in _rxm_frames(p)}
    assert kinds == {0x13, 0x14, 0x15}


def test_inconsistent_lengths_fall_back():
    raw = rawx_frame(1.0, 2000, 18, [RawxMeas(2.1e7, 3, 6, 0, 1000, 40, 5, True)])
    body = bytearray(raw[:-2])
    body[4] += 1  # length one byte more than numMeas implies
    assert parse_rxm(bytes(body) + b"\x00\x00\x00") is None
    assert parse_rxm(b"\xb5\x62\x01\x07\x00\x00\x00\x00") is None  # NAV-PVT: not ours


meas = st.builds(
    RawxMeas,
    pr_m=st.floats(1.9e7, 4.5e7),
    gnss_id=st.integers(0, 6),
    sv_id=st.integers(1, 63),
    sig_id=st.integers(0, 7),
    locktime_ms=st.integers(0, 64500),
    cn0_dbhz=st.integers(0, 60),
    pr_std_index=st.integers(0, 15),
    pr_valid=st.booleans(),
)


@settings(max_examples=150, deadline=None)
@given(
    tow=st.floats(0, 604799.999),
    week=st.integers(0, 4000),
    ms=st.lists(meas, min_size=0, max_size=40),
)
def test_rawx_encoder_read_by_pyubx2(tow, week, ms):
    msg = UBXReader.parse(rawx_frame(tow, week, 18, ms))
    assert msg.identity == "RXM-RAWX"
    assert (msg.rcvTow, msg.week, msg.leapS, msg.numMeas) == (tow, week, 18, len(ms))
    for i, m in enumerate(ms, start=1):
        k = f"_{i:02d}"
        assert getattr(msg, "prMes" + k) == (m.pr_m if m.pr_valid else 0.0)
        assert getattr(msg, "prValid" + k) == int(m.pr_valid)
        assert (getattr(msg, "gnssId" + k), getattr(msg, "svId" + k)) == (m.gnss_id, m.sv_id)
        assert getattr(msg, "sigId" + k) == m.sig_id
        assert getattr(msg, "locktime" + k) == m.locktime_ms
        assert getattr(msg, "cno" + k) == m.cn0_dbhz
        assert getattr(msg, "prStd" + k) == m.pr_std_index


svs = st.builds(
    MeasxSv,
    gnss_id=st.integers(0, 6),
    sv_id=st.integers(1, 63),
    cn0_dbhz=st.integers(0, 60),
    whole_chips=st.integers(0, 2045),
    code_phase_units=st.integers(0, (1 << 21) - 1),
    int_code_phase_ms=st.integers(0, 255),
)


@settings(max_examples=150, deadline=None)
@given(tow_ms=st.integers(0, 604_799_999), ss=st.lists(svs, min_size=0, max_size=40))
def test_measx_encoder_read_by_pyubx2(tow_ms, ss):
    bds_ms = (tow_ms - 14_000) % 604_800_000
    msg = UBXReader.parse(measx_frame(tow_ms, bds_ms, ss))
    assert msg.identity == "RXM-MEASX"
    assert (msg.gpsTOW, msg.bdsTOW, msg.numSv) == (tow_ms, bds_ms, len(ss))
    for i, s in enumerate(ss, start=1):
        k = f"_{i:02d}"
        assert (getattr(msg, "gnssId" + k), getattr(msg, "svId" + k)) == (s.gnss_id, s.sv_id)
        assert getattr(msg, "cNo" + k) == s.cn0_dbhz
        assert getattr(msg, "wholeChips" + k) == s.whole_chips
        # pyubx2 rounds scaled fields to 12 decimals; the LSB is 4.8e-7 ms
        assert math.isclose(
            getattr(msg, "codePhase" + k), s.code_phase_units * 2.0**-21, abs_tol=1e-12
        )
        assert getattr(msg, "intCodePhase" + k) == s.int_code_phase_ms


@pytest.mark.parametrize("path", CAPTURES, ids=lambda p: p.name)
def test_rawx_rows_map_alike_with_and_without_the_kept_signal_table(path: Path, monkeypatch):
    """What a RAWX row's (gnssId, svId, sigId) and a MEASX block's (gnssId, svId) mean is
    worked out once per mapper and kept (``RAWX_SIGNALS_KEPT`` of them): a mapper that keeps
    none, working each row out anew, gives the same epochs, subframes and counters, with
    every system read (the counters of other systems' signals and of other GNSS included)."""
    import drivers.ubx as ubx

    systems = frozenset({"C", "G", "E"})
    kept = UbxMapper(systems=systems)
    frames = _rxm_frames(path)
    got = [e for raw in frames for e in kept.on_frame(raw)] + kept.flush()
    monkeypatch.setattr(ubx, "RAWX_SIGNALS_KEPT", 0)
    anew = UbxMapper(systems=systems)
    want = [e for raw in frames for e in anew.on_frame(raw)] + anew.flush()
    assert [_epoch_key(e) for e in got] == [_epoch_key(e) for e in want]
    assert kept.counters == anew.counters
    has_rawx = any(raw[3] == 0x15 for raw in frames)
    assert not anew._rawx_signals and bool(kept._rawx_signals) == has_rawx
    has_measx = any(raw[3] == 0x14 for raw in frames)
    assert not anew._measx_sats and bool(kept._measx_sats) == has_measx
