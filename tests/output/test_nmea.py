"""NMEA 0183 sentences: every sentence parsed back by pynmeagps and by an independent hand
parser (comma split, XOR checksum), positions within 1 cm, times within 0.01 s."""

from __future__ import annotations

import datetime as dt
import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from pynmeagps import NMEAReader

from service.core.types import SatView, Velocity
from service.output.nmea import fix_utc, sentences_for_fix
from tests.support.fixes import SKY, declined_fix, ecef_m, hksc_fix
from tests.support.nmea import C_M_S, dm_deg, hand_parse, horiz_err_m, sec_of_day, utc_of_gpst


def fix_time(fix) -> dt.datetime:
    return utc_of_gpst(fix.gpst_week, fix.gpst_tow_s - fix.clock_bias_m / C_M_S)


def by_address(sentences: list[bytes]) -> dict[str, list[list[str]]]:
    out: dict[str, list[list[str]]] = {}
    for s in sentences:
        address, fields = hand_parse(s)
        out.setdefault(address, []).append(fields)
    return out


def test_hksc_fix_sentences_parse_back_to_the_fix():
    fix = hksc_fix()
    utc = fix_time(fix)
    sentences = sentences_for_fix(fix, utc=utc, time_known=True)
    addresses = [hand_parse(s)[0] for s in sentences]
    assert addresses == ["GNRMC", "GNGGA", "GBGSA", "GBGSV", "GBGSV", "GBGSV", "GNGST", "GNZDA"]
    for s in sentences:
        assert len(s) <= 82, s
        msg = NMEAReader.parse(s)
        assert msg is not None and msg.talker + msg.msgID == hand_parse(s)[0]

    want_sod = (utc - utc.replace(hour=0, minute=0, second=0, microsecond=0)).total_seconds()
    f = by_address(sentences)
    gga = f["GNGGA"][0]
    lat, lon = dm_deg(gga[1], gga[2]), dm_deg(gga[3], gga[4])
    assert horiz_err_m(lat, lon, fix.lat_deg, fix.lon_deg) < 0.01
    assert len(gga[1].split(".")[1]) == 7 and len(gga[3].split(".")[1]) == 7
    assert abs(sec_of_day(gga[0]) - want_sod) <= 0.005 + 1e-9
    assert gga[5] == "1" and int(gga[6]) == len(fix.used) == 8
    assert float(gga[7]) == pytest.approx(fix.hdop, abs=0.005)
    assert abs(float(gga[8]) + float(gga[10]) - fix.alt_m) < 0.01 and gga[9] == gga[11] == "M"
    parsed = NMEAReader.parse(sentences[1])
    assert horiz_err_m(parsed.lat, parsed.lon, fix.lat_deg, fix.lon_deg) < 0.01
    assert abs(parsed.alt - fix.alt_m) < 0.01

    rmc = f["GNRMC"][0]
    assert rmc[0] == gga[0] and rmc[1] == "A" and rmc[2:6] == gga[1:5]
    assert rmc[8] == utc.strftime("%d%m%y") and rmc[11] == "A"

    gsa = f["GBGSA"][0]
    assert gsa[:2] == ["A", "3"]
    assert [int(v) for v in gsa[2:14] if v] == sorted(int(p[1:]) for p in fix.used)
    assert [float(v) for v in gsa[14:17]] == pytest.approx([1.46, 0.84, 1.19], abs=0.006)
    assert gsa[17] == "4"  # NMEA 4.11 GNSS system ID: BeiDou

    seen = {}
    for k, gsv in enumerate(f["GBGSV"], start=1):
        assert gsv[0] == "3" and int(gsv[1]) == k and gsv[2] == str(len(SKY))
        assert gsv[-1] == "1"  # NMEA 4.11 signal ID: B1I
        groups = gsv[3:-1]
        assert len(groups) % 4 == 0 and len(groups) <= 16
        for j in range(0, len(groups), 4):
            seen[int(groups[j])] = groups[j + 1 : j + 4]
    assert sorted(seen) == sorted(int(s.prn[1:]) for s in SKY)
    for s in SKY:
        el, az, cno = seen[int(s.prn[1:])]
        assert int(el) == round(s.el_deg) and int(az) == round(s.az_deg)
        assert cno == ("" if math.isnan(s.cn0_dbhz) else str(round(s.cn0_dbhz)))

    gst = f["GNGST"][0]
    assert gst[0] == gga[0]
    rms, major, minor, orient, s_lat, s_lon, s_alt = (float(v) for v in gst[1:8])
    se, sn, su = fix.std_enu_m
    assert rms == pytest.approx(fix.resid_rms_m, abs=5e-4)
    assert (major, minor, s_lat, s_lon, s_alt) == pytest.approx((sn, se, sn, se, su), abs=5e-4)
    assert orient == 0.0  # the larger error is north-south

    zda = f["GNZDA"][0]
    assert zda[0] == gga[0] and [int(v) for v in zda[1:4]] == [utc.day, utc.month, utc.year]
    assert zda[4:6] == ["00", "00"]


@pytest.mark.parametrize(
    ("lat_deg", "lon_deg", "alt_m", "hemis"),
    [
        (-33.856784123, 151.215297432, 39.123, ("S", "E")),  # Sydney
        (-22.951916789, -43.210487654, 702.456, ("S", "W")),  # Rio de Janeiro
        (51.477928987, -0.001545123, 45.789, ("N", "W")),  # Greenwich, just west
        (0.000000050, 0.000000050, 1.0, ("N", "E")),
        (89.99999999, -179.99999999, 2835.0, ("N", "W")),
        (-77.846323, 166.668235, -31.5, ("S", "E")),  # McMurdo
    ],
)
def test_every_hemisphere_within_a_centimetre(lat_deg, lon_deg, alt_m, hemis):
    fix = hksc_fix(x_ecef_m=ecef_m(lat_deg, lon_deg, alt_m))
    assert fix.lat_deg == pytest.approx(lat_deg, abs=1e-10)
    sentences = sentences_for_fix(fix, utc=fix_time(fix))
    for s in sentences[:2]:
        address, fields = hand_parse(s)
        i = 1 if address.endswith("GGA") else 2
        assert (fields[i + 1], fields[i + 3]) == hemis
        lat, lon = dm_deg(fields[i], fields[i + 1]), dm_deg(fields[i + 2], fields[i + 3])
        assert horiz_err_m(lat, lon, lat_deg, lon_deg) < 0.01
        msg = NMEAReader.parse(s)
        assert horiz_err_m(msg.lat, msg.lon, lat_deg, lon_deg) < 0.01
        assert len(s) <= 82


def test_minutes_that_round_to_sixty_carry_into_the_degrees():
    fix = replace(hksc_fix(), lat_deg=22.99999999999, lon_deg=-113.99999999999)
    _, gga = hand_parse(sentences_for_fix(fix, utc=fix_time(fix))[1])
    assert gga[1:5] == ["2300.0000000", "N", "11400.0000000", "W"]
    assert horiz_err_m(dm_deg(gga[1], "N"), dm_deg(gga[3], "W"), 23.0, -114.0) < 1e-6


def test_10_hz_time_stamps_are_distinct_and_exact():
    stamps = []
    for k in range(30):
        fix = hksc_fix(gpst_tow_s=444954.0 + 0.1 * k, clock_bias_m=-87_654.321)
        utc = fix_time(fix)
        want = (utc - utc.replace(hour=0, minute=0, second=0, microsecond=0)).total_seconds()
        for s in sentences_for_fix(fix, utc=utc):
            address, fields = hand_parse(s)
            if address[2:] in ("GGA", "RMC", "GST", "ZDA"):
                assert abs(sec_of_day(fields[0]) - want) <= 0.005 + 1e-9, (k, s)
            if address.endswith("GGA"):
                stamps.append(fields[0])
                assert NMEAReader.parse(s).time == dt.time.fromisoformat(
                    f"{fields[0][:2]}:{fields[0][2:4]}:{fields[0][4:]}0000"
                )
    assert len(set(stamps)) == 30
    steps = [sec_of_day(b) - sec_of_day(a) for a, b in itertools.pairwise(stamps)]
    assert all(abs(step - 0.1) < 0.0101 for step in steps)


def test_rounding_to_the_hundredth_carries_into_the_date():
    fix = hksc_fix()
    utc = dt.datetime(2024, 12, 31, 23, 59, 59, 996_000)
    f = by_address(sentences_for_fix(fix, utc=utc))
    assert f["GNGGA"][0][0] == "000000.00"
    assert f["GNRMC"][0][8] == "010125"
    assert [int(v) for v in f["GNZDA"][0][1:4]] == [1, 1, 2025]


@pytest.mark.parametrize(
    ("tow_s", "hhmmss", "ddmmyy"),
    [
        (259215.50, "235959.50", "300615"),
        (259216.00, "235960.00", "300615"),  # the inserted second, 2015-06-30 23:59:60 UTC
        (259216.50, "235960.50", "300615"),
        (259216.999, "000000.00", "010715"),  # rounds to the hundredth past the leap
        (259217.25, "000000.25", "010715"),
    ],
)
def test_the_inserted_leap_second_reads_60(tow_s, hhmmss, ddmmyy):
    """IERS Bulletin C 49: UTC 2015-06-30 23:59:60 was inserted, GPST - UTC 16 s before and
    17 s after; GPS week 1851 began 2015-06-28, so 2015-07-01 00:00:00 UTC is tow
    3 * 86400 + 17 = 259217 s. The time comes as the publisher takes it (fix_utc)."""
    fix = hksc_fix(gpst_week=1851, gpst_tow_s=tow_s, clock_bias_m=0.0)
    f = by_address(sentences_for_fix(fix, utc=fix_utc(fix), time_known=True))
    assert f["GNGGA"][0][0] == f["GNRMC"][0][0] == f["GNZDA"][0][0] == hhmmss
    assert f["GNRMC"][0][8] == ddmmyy


def test_declined_fix_gives_gga_quality_0_and_rmc_void_only():
    sentences = sentences_for_fix(declined_fix(), utc=dt.datetime(2021, 6, 10, 3, 35, 36, 500_000))
    (a_rmc, rmc), (a_gga, gga) = (hand_parse(s) for s in sentences)
    assert (a_rmc, a_gga) == ("GNRMC", "GNGGA") and len(sentences) == 2
    assert gga[0] == "033536.50" and gga[1] == gga[3] == "" and gga[5] == "0"
    assert gga[7] == gga[8] == ""  # no HDOP, no altitude
    assert rmc[1] == "V" and rmc[2] == rmc[4] == "" and rmc[11] == "N"
    for s in sentences:
        assert NMEAReader.parse(s) is not None
    assert NMEAReader.parse(sentences[1]).quality == 0


@pytest.mark.parametrize(
    ("talker", "bds_talker"), [("GN", "GB"), ("GB", "GB"), ("BD", "BD"), ("GP", "GB")]
)
def test_talkers(talker, bds_talker):
    """GGA, RMC, GST, ZDA: the talker asked for; GSA and GSV (BeiDou satellites): BeiDou's."""
    fix = hksc_fix()
    addresses = [hand_parse(s)[0] for s in sentences_for_fix(fix, utc=fix_time(fix), talker=talker)]
    bds = ("GSA", "GSV")
    assert [a[:2] for a in addresses if not a.endswith(bds)] == [talker] * 4
    assert {a for a in addresses if a.endswith(bds)} == {bds_talker + "GSA", bds_talker + "GSV"}


def test_unknown_talker_is_refused():
    with pytest.raises(ValueError, match="talker"):
        sentences_for_fix(hksc_fix(), utc=dt.datetime(2021, 6, 10), talker="GL")


def test_zda_day_and_month_have_two_digits():
    """A hand-written sentence: ``dd,mm`` zero-padded, as NMEA 0183 writes ZDA."""
    utc = dt.datetime(2024, 9, 5, 7, 25, 1, 0)
    zda = sentences_for_fix(hksc_fix(), utc=utc)[-1]
    body = "GNZDA,072501.00,05,09,2024,00,00"
    checksum = 0
    for ch in body.encode():
        checksum ^= ch
    assert zda == f"${body}*{checksum:02X}\r\n".encode()


def test_zda_only_when_time_is_known():
    fix = hksc_fix()
    without = [
        hand_parse(s)[0] for s in sentences_for_fix(fix, utc=fix_time(fix), time_known=False)
    ]
    assert "GNZDA" not in without and without[-1] == "GNGST"


@pytest.mark.parametrize(
    ("lat_deg", "lon_deg", "alt_m", "hdop"),
    [
        (27.988056, 86.925278, 8848.86, 1.2),  # Everest
        (31.5590, 35.4732, -430.5, 2.3),  # Dead Sea shore
        (-16.5, -179.987654321, 3812.25, 15.4),  # poor geometry
        (-53.1638, -70.9171, 9999.987, 99.99),
    ],
)
def test_sentences_stay_within_82_characters_keeping_precision(lat_deg, lon_deg, alt_m, hdop):
    used = tuple(f"C{n:02d}" for n in (6, 9, 11, 12, 14, 16, 19, 20, 21, 22, 23, 24, 25, 26))
    fix = hksc_fix(
        x_ecef_m=ecef_m(lat_deg, lon_deg, alt_m),
        hdop=hdop,
        pdop=hdop * 1.7,
        vdop=hdop * 1.3,
        used=used,
        std_enu_m=(123.456, 4567.891, 12345.678),
        resid_rms_m=99.999,
    )
    sentences = sentences_for_fix(fix, utc=fix_time(fix))
    for s in sentences:
        assert len(s) <= 82, s
    f = by_address(sentences)
    gga = f["GNGGA"][0]
    assert len(gga[1].split(".")[1]) == 7 and len(gga[3].split(".")[1]) == 7
    lat, lon = dm_deg(gga[1], gga[2]), dm_deg(gga[3], gga[4])
    assert horiz_err_m(lat, lon, lat_deg, lon_deg) < 0.01
    assert abs(float(gga[8]) - alt_m) < 0.01 and abs(float(gga[7]) - hdop) < 0.051
    gsa = f["GBGSA"][0]
    assert [int(v) for v in gsa[2:14]] == [6, 9, 11, 12, 14, 16, 19, 20, 21, 22, 23, 24]
    gst = [float(v) for v in f["GNGST"][0][1:8]]
    # documented resolution: 0.1 m from 100 m, 1 m from 10 km
    assert abs(gst[4] - 4567.891) <= 0.05 and abs(gst[5] - 123.456) <= 0.05
    assert abs(gst[6] - 12345.678) <= 0.5


def test_gsv_leaves_unknown_angles_empty():
    sky = (SatView("C03", float("nan"), float("nan"), 33.0, False, True),)
    fix = hksc_fix(sky=sky)
    f = by_address(sentences_for_fix(fix, utc=fix_time(fix)))
    assert f["GBGSV"] == [["1", "1", "1", "3", "", "", "33", "1"]]


def test_gsa_names_beidou_by_its_talker_unless_told_otherwise():
    """GSA lists BeiDou satellites only: BeiDou's talker by default (gpsd 3.22 takes the
    constellation from it), BD with the BD talker, or the one asked for; the NMEA 4.11
    system ID is 4 in each."""
    fix = hksc_fix()
    for talker, gsa_talker, want in [
        ("GN", None, "GBGSA"),
        ("GP", None, "GBGSA"),
        ("BD", None, "BDGSA"),
        ("GN", "GN", "GNGSA"),
    ]:
        sentences = sentences_for_fix(fix, utc=fix_time(fix), talker=talker, gsa_talker=gsa_talker)
        addresses = [hand_parse(s)[0] for s in sentences]
        assert addresses[:3] == [f"{talker}RMC", f"{talker}GGA", want]
        assert hand_parse(sentences[2])[1][-1] == "4"
    with pytest.raises(ValueError, match="talker"):
        sentences_for_fix(fix, utc=fix_time(fix), gsa_talker="GA")


def test_gst_error_ellipse_comes_from_the_covariance():
    """A covariance whose major axis lies at 30 deg from north (east of north): the axes
    and orientation are the eigen-decomposition of the east-north block."""
    t = math.radians(30.0)
    u = np.array([math.sin(t), math.cos(t)])  # (east, north) of the major axis
    v = np.array([math.cos(t), -math.sin(t)])
    en = 4.0**2 * np.outer(u, u) + 1.5**2 * np.outer(v, v)
    cov = ((en[0, 0], en[0, 1], 0.0), (en[1, 0], en[1, 1], 0.0), (0.0, 0.0, 9.0))
    fix = hksc_fix(std_enu_m=(math.sqrt(en[0, 0]), math.sqrt(en[1, 1]), 3.0), cov_enu_m2=cov)
    gst = by_address(sentences_for_fix(fix, utc=fix_time(fix)))["GNGST"][0]
    _rms, major, minor, orient, s_lat, s_lon, s_alt = (float(x) for x in gst[1:8])
    assert (major, minor) == pytest.approx((4.0, 1.5), abs=5e-4)
    assert orient == pytest.approx(30.0, abs=0.05)
    assert (s_lat, s_lon, s_alt) == pytest.approx(
        (math.sqrt(en[1, 1]), math.sqrt(en[0, 0]), 3.0), abs=5e-4
    )


def test_speed_and_course_in_rmc_and_vtg():
    """A fix moving at 5 m/s toward 036.87 deg (east 3, north 4): RMC and VTG carry
    5 * 3600 / 1852 = 9.719 kn, VTG 18.0 km/h, both the course; pynmeagps reads them back.
    A course whose sigma exceeds 10 deg is left out (static receivers), the speed is not."""
    vel = Velocity((3.0, 4.0, 0.0), (0.02, 0.02, 0.05), 5.0, 0.02, 36.8699, 0.23, 12.0, 0.05)
    fix = replace(hksc_fix(), velocity=vel)
    sentences = sentences_for_fix(fix, utc=fix_time(fix))
    assert [hand_parse(s)[0] for s in sentences[:3]] == ["GNRMC", "GNVTG", "GNGGA"]
    rmc, vtg = NMEAReader.parse(sentences[0]), NMEAReader.parse(sentences[1])
    assert rmc.spd == pytest.approx(9.719, abs=5e-4) and rmc.cog == pytest.approx(36.87)
    assert vtg.sogn == pytest.approx(9.719, abs=5e-4) and vtg.sogk == pytest.approx(18.0)
    assert vtg.cogt == pytest.approx(36.87) and vtg.cogtUnit == "T" and vtg.posMode == "A"
    vague = replace(fix, velocity=replace(vel, std_course_deg=10.5))
    _, rmc_fields = hand_parse(sentences_for_fix(vague, utc=fix_time(fix))[0])
    assert rmc_fields[6] == "9.719" and rmc_fields[7] == ""
    # no velocity: no VTG and RMC's speed and course fields are empty
    plain = sentences_for_fix(hksc_fix(), utc=fix_time(fix))
    assert not any(b"VTG" in s for s in plain)
    _, rmc_fields = hand_parse(plain[0])
    assert rmc_fields[6] == rmc_fields[7] == ""
