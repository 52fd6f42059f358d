"""RINEX 4 files (4.00-4.02) read as their RINEX 3 content: the navigation file's records
each open with a ``> EPH|STO|EOP|ION SV MSG`` line, and the Klobuchar coefficients come in
``ION`` records instead of the header's ``IONOSPHERIC CORR``; an observation file's records
are those of RINEX 3.05.

No RINEX 4 recording is at hand, so the real ones are written here in RINEX 4 as its
format defines (4.00, section 5.4 and the navigation appendix): the HKSC station's RINEX 3.04
mixed nav file (BeiDou, GPS, Galileo, GLONASS, QZSS ... records, the BDS and GPS Klobuchar
header records) and its observation file. The expected values are what the RINEX 3 reader
reads from the RINEX 3 files, which tests/drivers/test_rinex.py checks against georinex.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest

from drivers.rinex import RinexObsReader, read_nav
from service.core.errors import FramingError
from tests.support.paths import DATA

HKSC = DATA / "hksc-2021"
NAV3 = HKSC / "hksc1610.nav"
OBS3 = HKSC / "hksc1610.obs"
GEO_PRNS = {f"C{n:02d}" for n in (*range(1, 6), *range(59, 64))}  # D2: the GEOs


def _header_and_records(path: Path) -> tuple[list[str], list[list[str]]]:
    lines = path.read_text().splitlines(keepends=True)
    end = next(k for k, line in enumerate(lines) if "END OF HEADER" in line)
    records: list[list[str]] = []
    for line in lines[end + 1 :]:
        if line[:1].strip():
            records.append([line])
        elif line.strip():
            records[-1].append(line)
    return lines[: end + 1], records


def _message_type(rec: list[str]) -> str:
    prn = rec[0][:3]
    system = prn[0]
    if system == "E":  # data sources (orbit line 5, field 2): bits 0 and 2 I/NAV
        return "INAV" if int(float(rec[5][23:42].replace("D", "E"))) & 0b101 else "FNAV"
    if system == "C":
        return "D2" if prn in GEO_PRNS else "D1"
    return {"R": "FDMA", "S": "SBAS"}.get(system, "LNAV")


def _d19(values: list[float]) -> str:
    return "".join(f"{v:19.12E}" for v in values)


def _klobuchar_record(sv: str, msg: str, header: list[str], a: str, b: str) -> str:
    """A RINEX 4 Klobuchar ION record of the header's ``a``/``b`` IONOSPHERIC CORR values:
    the transmission epoch and alpha0-2, then alpha3 and beta0-2, then beta3 and the region
    (0: wide area)."""
    vals: dict[str, list[float]] = {}
    for line in header:
        if line[60:80].strip() == "IONOSPHERIC CORR" and line[:4] in (a, b):
            fields = [line[5 + 12 * i : 17 + 12 * i] for i in range(4)]
            vals[line[:4]] = [float(f.replace("D", "E")) for f in fields]
    alpha, beta = vals[a], vals[b]
    return (
        f"> ION {sv} {msg}\n"  # the satellite that sent it
        f"    2021 06 10 00 00 00{_d19(alpha[:3])}\n"
        f"    {_d19([alpha[3], *beta[:3]])}\n"
        f"    {_d19([beta[3], 0.0])}\n"
    )


def _nav4(tmp_path: Path) -> Path:
    header, records = _header_and_records(NAV3)
    out = ["     4.00           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE\n"]
    out += [
        line
        for line in header[1:]
        if line[60:80].strip() not in ("IONOSPHERIC CORR", "TIME SYSTEM CORR")
    ]
    out.append(_klobuchar_record("C01", "D1D2", header, "BDSA", "BDSB"))
    # a QZSS Klobuchar record first: not GPS's, though of the same message type
    out.append(_klobuchar_record("J01", "LNAV", header, "BDSA", "BDSB"))
    out.append(_klobuchar_record("G01", "LNAV", header, "GPSA", "GPSB"))
    first_gps = next(r for r in records if r[0][0] == "G")
    # records of other message types, whose layouts differ: skipped, counted
    out.append("> EPH G01 CNAV\n" + "".join(first_gps) + first_gps[-1])
    out.append("> STO G01 LNAV\n" + first_gps[0] + first_gps[1])
    out.append("> EOP G LNAV\n" + first_gps[0] + first_gps[1] + first_gps[2] + first_gps[3])
    for rec in records:
        if rec[0][0] == "R" and len(rec) == 4:  # RINEX 3.05/4: a fifth line, status/health
            rec = [*rec, "    " + _d19([0.0, 0.0, 0.0, 0.0]) + "\n"]
        out.append(f"> EPH {rec[0][:3]} {_message_type(rec)}\n" + "".join(rec))
    path = tmp_path / "hksc1610.rnx"
    path.write_text("".join(out))
    return path


def test_a_rinex4_nav_file_gives_what_its_rinex3_form_gives(tmp_path, caplog):
    v4 = _nav4(tmp_path)
    systems = ("C", "G", "E")
    three = read_nav(NAV3, systems)
    with caplog.at_level(logging.WARNING):
        four = read_nav(v4, systems)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert four.version == 4.0
    assert four.ephemerides == three.ephemerides
    assert sum(len(s) for s in four.ephemerides.values()) > 100
    assert {p[0] for p in four.ephemerides} == set(systems)
    assert four.iono_bds == three.iono_bds is not None
    assert four.iono_gps == three.iono_gps is not None
    assert four.leap_seconds == three.leap_seconds
    assert four.counters["records4_EPH_G_CNAV"] == 1
    assert four.counters["records4_STO_G_LNAV"] == 1
    assert four.counters["records4_EOP_G_LNAV"] == 1
    assert four.counters["records4_ION_C_D1D2"] == four.counters["records4_ION_G_LNAV"] == 1
    assert four.counters["records4_ION_J_LNAV"] == 1
    for system in "CGERJ":  # every record of the v3 file, counted by system, as there
        assert four.counters.get(f"records_{system}") == three.counters.get(f"records_{system}")


def test_a_rinex4_obs_file_gives_what_its_rinex3_form_gives(tmp_path):
    lines = OBS3.read_text().splitlines(keepends=True)
    assert lines[0].startswith("     3.04")
    v4 = tmp_path / "hksc1610.obs"
    v4.write_text("     4.00" + lines[0][9:] + "".join(lines[1:]))
    three, four = list(RinexObsReader(OBS3)), list(RinexObsReader(v4))
    assert len(four) == len(three) == 205
    for a, b in zip(three, four, strict=True):
        assert (a.gpst_week, a.gpst_tow_s, a.prn) == (b.gpst_week, b.gpst_tow_s, b.prn)
        assert a.pr_m.tobytes() == b.pr_m.tobytes()


def _damaged(tmp_path: Path, edit, system: str = "C") -> Path:
    """The RINEX 4 form of the HKSC nav file with its first ``> EPH`` record of ``system``
    (lines of the file, the ``>`` line first) changed by ``edit``."""
    lines = _nav4(tmp_path).read_text().splitlines(keepends=True)
    at = next(k for k, line in enumerate(lines) if line.startswith(f"> EPH {system}"))
    lines[at : at + 9] = edit(lines[at : at + 9])
    damaged = tmp_path / "damaged.rnx"
    damaged.write_text("".join(lines))
    return damaged


@pytest.mark.parametrize(
    ("name", "edit"),
    [
        ("a '>' line alone", lambda r: [">\n", *r[1:]]),
        ("no message type", lambda r: [" ".join(r[0].split()[:3]) + "\n", *r[1:]]),
        ("an unknown record type", lambda r: [r[0].replace("EPH", "EHP"), *r[1:]]),
        ("its first data line lost", lambda r: [r[0], *r[2:]]),
        ("no data lines", lambda r: [r[0]]),
        ("another system's '>' line", lambda r: [r[0].replace("> EPH C", "> EPH G"), *r[1:]]),
        ("another system's type", lambda r: ["> EPH G06 LNAV\n", *r[1:]]),
        ("another satellite's '>' line", lambda r: [r[0][:7] + "63" + r[0][9:], *r[1:]]),
        ("a line missing", lambda r: r[:-1]),
    ],
)
def test_a_damaged_rinex4_record_is_an_error_naming_its_line(tmp_path, name, edit):
    """Each damage that would lose a BeiDou set is a FramingError at the record's line, as
    the RINEX 3 reader's damaged records are, never a set silently dropped."""
    damaged = _damaged(tmp_path, edit)
    with pytest.raises(FramingError, match=rf"^{re.escape(str(damaged))}:\d+: ") as err:
        read_nav(damaged, ("C", "G", "E"))
    lineno = int(str(err.value).split(":")[1])
    text = damaged.read_text().splitlines()
    assert text[lineno - 1].startswith((">", "C")), (name, text[lineno - 1])


def test_a_damaged_record_of_a_system_not_read_is_a_warning(tmp_path, caplog):
    """The same damage (a GPS record's first data line lost) where the caller does not read
    GPS (a BeiDou-only solve) is logged and counted; every BeiDou set is read."""
    damaged = _damaged(tmp_path, lambda r: [r[0], *r[2:]], system="G")
    with caplog.at_level(logging.WARNING):
        nav = read_nav(damaged, ("C",))
    assert nav.counters["records_G_odd_length"] == 1
    assert [r.getMessage() for r in caplog.records if "without its data line" in r.getMessage()]
    assert nav.ephemerides == read_nav(NAV3, ("C",)).ephemerides
