"""GGTO, the broadcast GST - GPST offset (OS SIS ICD 5.1.8): read from a RINEX 3 nav
header's ``TIME SYSTEM CORR`` ``GAGP`` record, carried to the pipeline with the nav file's
ephemerides, recorded in STATUS (``ggto_ns``) and never applied to ranges (one receiver
clock per system absorbs it; docs/method.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.rinex import read_nav
from drivers.source import _nav_events
from service.core.counters import Counters
from service.core.ephemeris import EphemerisStore
from service.core.types import TimeOffset
from service.engine.pipeline import Pipeline
from tests.support.paths import DATA

HKSC_NAV = DATA / "hksc-2021" / "hksc1610.nav"
# RINEX 3.04 Table A5: A4,1X,D17.10,D16.9,1X,I6,1X,I4 (then source and UTC id, unused here)
GAGP = "GAGP  2.3283064365D-09-4.440892099D-15 345600 2161          TIME SYSTEM CORR    \n"


def _with_gagp(tmp_path: Path, record: str = GAGP) -> Path:
    """The real HKSC nav file with one GAGP record added to its header."""
    lines = HKSC_NAV.read_text().splitlines(keepends=True)
    at = next(i for i, line in enumerate(lines) if "TIME SYSTEM CORR" in line)
    path = tmp_path / "hksc1610-gagp.nav"
    path.write_text("".join([*lines[:at], record, *lines[at:]]))
    return path


@pytest.mark.parametrize("damage", [(38, 45, "  x4560"), (5, 22, " " * 17)])
def test_an_unreadable_gagp_record_is_skipped_not_the_file(tmp_path: Path, damage):
    """The GGTO is only recorded: a garbled reference time or blank a0 loses it alone; the
    file's ephemerides are read as without the record."""
    start, end, text = damage
    record = GAGP[:start] + text + GAGP[end:]
    nav = read_nav(_with_gagp(tmp_path, record), "CGE")
    assert nav.ggto is None
    assert nav.ephemerides == read_nav(HKSC_NAV, "CGE").ephemerides


def test_the_real_file_has_no_gagp_and_gives_none():
    assert read_nav(HKSC_NAV, "CGE").ggto is None


def test_gagp_record_reads_as_the_ggto(tmp_path: Path):
    nav = read_nav(_with_gagp(tmp_path), "CGE")
    off = nav.ggto
    assert off == TimeOffset("GAGP", 2.3283064365e-09, -4.440892099e-15, 345600.0, 2161, "rinex")
    # A0G + A1G (t - t0G + 604800 (WN - WN0G)), ICD 5.1.8: a day after t0G
    assert off.at_s(2161, 345600.0 + 86400.0) == pytest.approx(
        2.3283064365e-09 - 4.440892099e-15 * 86400.0, rel=1e-12
    )
    assert off.at_s(2162, 0.0) == pytest.approx(2.3283064365e-09 - 4.440892099e-15 * 259200.0)


def test_nav_file_ggto_reaches_the_pipeline_and_status(tmp_path: Path):
    events = _nav_events(_with_gagp(tmp_path), Counters(), "CGE")
    offsets = [e for e in events if isinstance(e, TimeOffset)]
    assert len(offsets) == 1
    pipe = Pipeline(store=EphemerisStore())
    assert pipe.ggto_ns() is None
    pipe.set_time_offset(offsets[0])
    assert pipe.counters["ggto_rinex"] == 1
    assert pipe.ggto_ns() == pytest.approx(2.328, abs=1e-3)  # at its own reference time
