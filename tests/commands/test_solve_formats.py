"""`bdsfix solve` CSV and NMEA outputs, checked with independent parsers."""

import csv
import functools
import io
import operator

import pynmeagps

from service.commands.cli import main
from tests.support.paths import DATA

HK = DATA / "hksc-2021"


def _run(tmp_path, fmt):
    out = tmp_path / f"out.{fmt}"
    assert (
        main(
            [
                "solve",
                str(HK / "hksc1610.obs"),
                str(HK / "hksc1610.nav"),
                "--format",
                fmt,
                "--out",
                str(out),
            ]
        )
        == 0
    )
    return out.read_text()


def test_csv_rows(tmp_path):
    rows = list(csv.DictReader(io.StringIO(_run(tmp_path, "csv"))))
    assert len(rows) == 2 * 205
    fast = [r for r in rows if r["solver"] == "fast"]
    assert all(r["mode"] == "fast" and int(r["n_full"]) == 5 for r in fast)
    assert abs(float(fast[0]["x_ecef_m"]) + 2414266.9) < 5.0


def test_nmea_sentences_parse_and_checksum(tmp_path):
    text = _run(tmp_path, "nmea")
    lines = text.splitlines()
    gga = [ln for ln in lines if ln.startswith("$GNGGA")]
    assert len(gga) == 205
    for ln in lines:
        body, _, cs = ln[1:].partition("*")
        assert int(cs, 16) == functools.reduce(operator.xor, body.encode(), 0)
        msg = pynmeagps.NMEAReader.parse(ln)
        assert msg is not None
    first = pynmeagps.NMEAReader.parse(gga[0])
    assert abs(first.lat - 22.3222) < 1e-3 and abs(first.lon - 114.1412) < 1e-3
    # every system by default: the first fix uses 16 BeiDou, 11 GPS and 6 Galileo satellites
    assert first.quality == 1 and first.numSV == 16 + 11 + 6
    for talker in ("GP", "GB", "GA"):  # one GSA per system (NMEA 4.11 system IDs 1, 4, 3)
        assert any(ln.startswith(f"${talker}GSA") for ln in lines), talker
    assert any(ln.startswith("$GBGSV") and ln.split("*")[0].endswith(",1") for ln in lines)
    assert any(ln.startswith("$GNZDA,033536.00,10,06,2021") for ln in lines)
