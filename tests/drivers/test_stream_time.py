"""Time for streams that do not carry it in every message, on the real captures.

- RTCM MSM gives only a time of week: the GPS week comes from the stream's own broadcast
  ephemerides (1042 BDS, 1019 GPS, 1044 QZSS, 1045/1046 Galileo), their truncated weeks
  resolved against the system clock or a sane epoch; an epoch before any week is passed on
  without one (the pipeline declines it), never dropped.
- u-blox SFRBX without RAWX: subframes take the time of the latest NAV-TIMEGPS (or
  NAV-PVT) navigation epoch.

Independent references: pyrtcm's and pyubx2's own stream readers.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from pyrtcm import RTCMReader
from pyubx2 import UBXReader

from drivers.framing import Framer, WeekContext
from drivers.protocols import PROTOCOLS
from drivers.rtcm import message_number
from drivers.source import StreamDecoder
from service.core.timebase import MIN_SANE_GPS_WEEK, nearest_week
from service.core.types import MeasurementEpoch, NavSubframe
from tests.support.paths import DATA

HIROSHIMA = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
HIROSHIMA_WEEK = 2240  # 2022-12-13 (the capture's README)
F9P_SFRBX = DATA / "ublox-logs" / "ublox-zed-f9p-sfrbx.log"
X20P = DATA / "ublox-logs" / "ublox-x20p.log"
NAV_TIMEGPS = b"\x01\x20"


def decode(data: bytes, dec: StreamDecoder | None = None) -> tuple[list, StreamDecoder]:
    dec = dec if dec is not None else StreamDecoder()
    return dec.feed(data) + dec.flush(), dec


def epochs_of(events) -> list[MeasurementEpoch]:
    return [e for e in events if isinstance(e, MeasurementEpoch)]


def frames_of(path: Path) -> list:
    framer = Framer(PROTOCOLS)
    return framer.feed(path.read_bytes()) + framer.flush()


# --- RTCM: the week from the stream's ephemerides -------------------------------------------
def test_rtcm_week_from_the_first_ephemeris_of_any_system():
    """OEM729 RTCM without --gps-week: 60 epochs, as with the week given; the 6 before the
    first ephemeris (Galileo 1045/1046 after 18 BDS MSM, 1042 only after 33) have no week,
    every later one has the week of the capture."""
    epochs = epochs_of(decode(HIROSHIMA.read_bytes())[0])
    given = epochs_of(decode(HIROSHIMA.read_bytes(), StreamDecoder(gps_week=HIROSHIMA_WEEK))[0])
    assert len(epochs) == len(given) == 60
    assert [e.week_known for e in epochs] == [False] * 6 + [True] * 54
    assert {e.gpst_week for e in epochs[6:]} == {e.gpst_week for e in given} == {HIROSHIMA_WEEK}
    for e, g in zip(epochs, given, strict=True):
        assert (e.gpst_tow_s, e.prn) == (g.gpst_tow_s, g.prn)
    # the first ephemeris in the stream is Galileo's, after the 6th epoch's MSM
    msm_before = 0
    for f in frames_of(HIROSHIMA):
        n = message_number(f.raw)
        if n in (1019, 1042, 1044, 1045, 1046):
            assert n == 1045 and msm_before == 18  # 3 x 1127 per epoch
            break
        msm_before += n == 1127
    _, dec = decode(HIROSHIMA.read_bytes())
    assert dec.week.source == "RTCM 1045 (Galileo F/NAV ephemeris)"
    assert dec.counters["msm_no_week"] == 18


@pytest.mark.parametrize("clock_week", [None, 2394, 1800], ids=["unset", "2026", "2014"])
def test_gps_ephemeris_alone_resolves_its_10_bit_week(clock_week):
    """The same stream with the 1042/1044/1045/1046 frames taken out: the GPS 1019 week
    (10 bits, 192 here) gives week 2240 whether the system clock is unset (the sane epoch
    is used), right, or eight years early."""
    others = (1042, 1044, 1045, 1046)
    kept = [f.raw for f in frames_of(HIROSHIMA) if message_number(f.raw) not in others]
    first_1019 = next(i for i, raw in enumerate(kept) if message_number(raw) == 1019)
    assert int(RTCMReader.parse(kept[first_1019]).DF076) == HIROSHIMA_WEEK % 1024
    msm_before = sum(message_number(raw) == 1127 for raw in kept[:first_1019])
    dec = StreamDecoder()
    dec.week.clock_week = lambda: clock_week
    epochs = epochs_of(decode(b"".join(kept), dec)[0])
    assert len(epochs) == 60
    unknown = [e for e in epochs if not e.week_known]
    assert len(unknown) == msm_before // 3 and epochs[: len(unknown)] == unknown
    assert {e.gpst_week for e in epochs[len(unknown) :]} == {HIROSHIMA_WEEK}
    assert dec.week.source == "RTCM 1019 (GPS ephemeris)"


def test_nearest_week_resolves_truncated_weeks():
    assert nearest_week(192, 1024, 2394) == 2240
    assert nearest_week(192, 1024, MIN_SANE_GPS_WEEK) == 2240
    assert nearest_week(192, 1024, 1800) == 2240
    assert nearest_week(192, 1024, 1100) == 1216
    assert nearest_week(0, 1024, 2047) == 2048  # the 2019 rollover
    wc = WeekContext(clock_week=lambda: None)
    assert wc.broadcast_week(1216, 4096, 1024) == 2240  # Galileo: GST week 0 = GPS 1024
    wc.set_exact(1500, 0.0)
    assert wc.broadcast_week(1500 % 1024, 1024) == 1500  # the known week wins over clocks


def test_week_sources_by_rank(caplog):
    """A hint (--gps-week, the system clock) gives way to the stream's ephemeris week, which
    gives way to the receiver's own; a lower rank never replaces a higher one, and a hint
    a stream contradicts by more than a week is logged."""
    wc = WeekContext(2300)
    assert wc.resolve(100.0) == 2300 and wc.source == "--gps-week"
    with caplog.at_level(logging.INFO, logger="drivers.framing"):
        wc.set_approx(2240, 176400.0, "RTCM 1042")
    assert wc.source == "RTCM 1042" and wc.resolve(176500.0) == 2240
    assert "GPS week 2240 from RTCM 1042 replaces week 2300 from --gps-week" in caplog.text
    wc.set_hint(2394, 0.0)
    assert wc.resolve(176501.0) == 2240 and not wc.exact
    wc.set_exact(2241, 10.0)
    wc.set_approx(2240, 176400.0, "RTCM 1042")
    assert wc.exact and wc.resolve(11.0) == 2241 and wc.source == "receiver time"
    fresh = WeekContext()
    assert not fresh.known and fresh.resolve(5.0) is None


# --- u-blox: SFRBX time from the navigation epoch --------------------------------------------
def _nav_times(path: Path) -> list[tuple[str, int, float]]:
    out = []
    with open(path, "rb") as stream:
        for _, msg in UBXReader(stream, protfilter=2, quitonerror=0):
            if msg.identity == "NAV-TIMEGPS":
                out.append(("T", msg.week, msg.iTOW * 1e-3 + msg.fTOW * 1e-9))
            elif msg.identity == "RXM-SFRBX" and msg.gnssId == 3:
                out.append(("S", 0, 0.0))
    return out


def test_sfrbx_without_rawx_takes_the_time_of_nav_timegps():
    """ZED-F9P log with SFRBX and no RAWX: all 11 BDS B1I subframes come out, each tagged
    with the NAV-TIMEGPS before it (pyubx2's reading), and each such time is one subframe
    after its SOW (GPST = BDT + 14 s; the SOW marks the subframe's start)."""
    events, dec = decode(F9P_SFRBX.read_bytes())
    subs = [e for e in events if isinstance(e, NavSubframe)]
    assert len(subs) == dec.counters["sfrbx_bds"] == 11 and dec.counters["sfrbx_no_time"] == 0
    want, last = [], None
    for kind, week, tow in _nav_times(F9P_SFRBX):
        if kind == "T":
            last = (week, tow)
        else:
            want.append(last)
    assert [s.gpst_week for s in subs] == [w for w, _ in want]
    assert [s.gpst_tow_s for s in subs] == pytest.approx([t for _, t in want], abs=1e-9)
    for s in subs:
        assert 0.0 <= s.gpst_tow_s - 14.0 - (s.sow_s + 6.0) <= 0.2


def test_sfrbx_takes_the_time_of_nav_pvt_without_nav_timegps():
    """The same log with every NAV-TIMEGPS frame taken out: NAV-PVT (date and time valid)
    gives the same times, to its millisecond."""
    with_timegps = [e for e in decode(F9P_SFRBX.read_bytes())[0] if isinstance(e, NavSubframe)]
    data = b"".join(f.raw for f in frames_of(F9P_SFRBX) if f.raw[2:4] != NAV_TIMEGPS)
    events, dec = decode(data)
    subs = [e for e in events if isinstance(e, NavSubframe)]
    assert dec.counters["ubx:NAV-TIMEGPS"] == 0 and dec.counters["ubx:NAV-PVT"] == 19
    assert [s.words for s in subs] == [s.words for s in with_timegps]
    for a, b in zip(subs, with_timegps, strict=True):
        assert a.gpst_week == b.gpst_week and abs(a.gpst_tow_s - b.gpst_tow_s) < 1e-3


def test_x20p_subframes_get_their_time_but_are_not_b1i():
    """X20P log: NAV-TIMEGPS times its 100 BDS subframes, which are B3I D1 (sigId 4) and
    B-CNAV (sigId 6, 8): counted as unmapped, as the service decodes B1I only."""
    events, dec = decode(X20P.read_bytes())
    assert dec.counters["sfrbx_bds"] == dec.counters["sfrbx_unmapped"] == 100
    assert dec.counters["sfrbx_no_time"] == 0 and not events


def test_a_nav_pvt_with_a_damaged_year_gives_no_week():
    """The PolyU F9P capture's first UBX-NAV-PVT with its year field made 1284 and the
    checksum made again (a frame damaged before its checksum was computed, or garbage that
    passes it): flagged valid, but no week is taken from it (counted ``nav_pvt_bad_date``);
    the same frame undamaged gives the capture's week (2333: 2024-09-25)."""
    from drivers.ubx import fletcher8

    capture = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
    frames = Framer(PROTOCOLS).feed(capture.read_bytes()[:1_000_000])
    pvt = next(f.raw for f in frames if f.protocol == "ubx" and f.raw[2:4] == b"\x01\x07")
    body = bytearray(pvt[2:-2])
    assert int.from_bytes(body[4 + 4 : 4 + 6], "little") == 2024  # year (payload offset 4)
    body[4 + 4 : 4 + 6] = (1284).to_bytes(2, "little")
    damaged = bytes(pvt[:2]) + bytes(body) + fletcher8(body)
    dec = StreamDecoder(gps_week=2300)
    dec.feed(damaged)
    assert dec.counters["nav_pvt_bad_date"] == 1
    assert dec.week.resolve(0.0) == 2300
    dec = StreamDecoder(gps_week=2300)
    dec.feed(pvt)
    assert dec.counters["nav_pvt_bad_date"] == 0
    assert dec.week.source == "UBX NAV-PVT" and dec.week.resolve(285_000.0) == 2333
