"""An independent NMEA 0183 reader (comma split, XOR checksum) and the time helpers the
NMEA and publisher tests check sentences with."""

from __future__ import annotations

import datetime as dt
import functools
import math
import operator

C_M_S = 299_792_458.0
R_EARTH_M = 6_371_000.0


def utc_of_gpst(week: int, tow_s: float) -> dt.datetime:
    """GPST to UTC with GPST - UTC = 18 s (in force since 2017-01-01, IERS Bulletin C)."""
    return dt.datetime(1980, 1, 6) + dt.timedelta(weeks=week, seconds=tow_s - 18.0)


def hand_parse(sentence: bytes) -> tuple[str, list[str]]:
    """(address, fields) of one sentence, checking framing and the XOR checksum."""
    text = sentence.decode("ascii")
    assert text.startswith("$") and text.endswith("\r\n"), text
    body, star, cs = text[1:-2].rpartition("*")
    assert star and len(cs) == 2, text
    assert int(cs, 16) == functools.reduce(operator.xor, body.encode("ascii"), 0), text
    address, *fields = body.split(",")
    return address, fields


def dm_deg(value: str, hemi: str) -> float:
    """(d)ddmm.mmmmmmm + hemisphere to signed degrees."""
    dot = value.index(".")
    minutes = float(value[dot - 2 :])
    assert 0.0 <= minutes < 60.0, value
    return (int(value[: dot - 2]) + minutes / 60.0) * (-1.0 if hemi in ("S", "W") else 1.0)


def sec_of_day(hhmmss: str) -> float:
    return int(hhmmss[:2]) * 3600 + int(hhmmss[2:4]) * 60 + float(hhmmss[4:])


def horiz_err_m(lat_a: float, lon_a: float, lat_b: float, lon_b: float) -> float:
    dn = math.radians(lat_a - lat_b) * R_EARTH_M
    de = math.radians(lon_a - lon_b) * R_EARTH_M * math.cos(math.radians(lat_b))
    return math.hypot(dn, de)
