"""NMEA of a fix over BeiDou, GPS and Galileo (issue 19): one GSA per system with its NMEA 4.11
system ID, one GSV group per system under its talker, read back by pynmeagps and by gpsd.

The fixes are real: HKSC's first epochs solved by SPP with --systems C,G,E semantics (RINEX
obs and nav of ../shared/data/hksc-2021), with their sky views.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import time

import pytest
from pynmeagps import NMEAReader

from drivers.rinex import RinexObsReader, read_nav
from service.core.ephemeris import EphemerisStore
from service.engine.solver import IonoSet, SolverConfig, solve
from service.output.nmea import sentences_for_fix
from service.output.publish import Publishers
from service.output.sinks.nmea_tcp import NmeaTcpServer
from tests.support.gpsd import gpsd_watching
from tests.support.nmea import C_M_S, hand_parse, utc_of_gpst
from tests.support.paths import DATA

HKSC = DATA / "hksc-2021"
HANG_S = 60.0  # waits end here only for a hung run; nothing is timed
GSA_MAX_SV = 12  # NMEA 0183 GSA carries 12 satellite IDs
# NMEA 4.11: talker, GSA system ID, GSV signal ID; gpsd's gnssid (0 GPS, 2 Galileo, 3 BeiDou)
EXPECTED = {"C": ("GB", "4", "1", 3), "G": ("GP", "1", "1", 0), "E": ("GA", "3", "7", 2)}


@functools.cache
def _fixes(n: int = 3):
    nav = read_nav(HKSC / "hksc1610.nav", systems="CGE")
    store = EphemerisStore()
    for sets in nav.ephemerides.values():
        store.add_all(sets)
    iono = IonoSet.of([nav.iono_bds, nav.iono_gps])
    epochs = itertools.islice(RinexObsReader(HKSC / "hksc1610.obs", systems="CGE"), n)
    return [solve(ep, store, iono, SolverConfig(), "spp", with_sky=True) for ep in epochs]


def _utc(fix):
    return utc_of_gpst(fix.gpst_week, fix.gpst_tow_s - fix.clock_bias_m / C_M_S)


def test_one_gsa_and_gsv_group_per_system():
    fix = _fixes()[0]
    assert fix.ok and {p[0] for p in fix.used} == {"C", "G", "E"}
    sentences = sentences_for_fix(fix, utc=_utc(fix))
    parsed = [hand_parse(s) for s in sentences]
    assert [a for a, _ in parsed][:2] == ["GNRMC", "GNGGA"]  # no velocity: no VTG
    for letter, (talker, system_id, signal_id, _) in EXPECTED.items():
        gsa = [f for a, f in parsed if a == talker + "GSA"]
        assert len(gsa) == 1, letter
        ids = [int(x) for x in gsa[0][2:14] if x]
        mine = sorted(int(p[1:]) for p in fix.used if p[0] == letter)
        assert ids == mine[:GSA_MAX_SV] and gsa[0][17] == system_id
        gsv = [f for a, f in parsed if a == talker + "GSV"]
        in_view = sorted(int(s.prn[1:]) for s in fix.sky if s.prn[0] == letter)
        assert int(gsv[0][2]) == len(in_view)
        assert all(f[-1] == signal_id for f in gsv)
        # and pynmeagps reads each of them
    for s in sentences:
        assert NMEAReader.parse(s.decode()).msgID


def test_a_beidou_only_fix_keeps_its_sentences():
    """The same fix cut to its BeiDou rows gives one GBGSA and GBGSV only (as before)."""
    fix = _fixes()[0]
    bds = dataclasses.replace(
        fix,
        used=tuple(p for p in fix.used if p[0] == "C"),
        sky=tuple(s for s in fix.sky if s.prn[0] == "C"),
    )
    talkers = [hand_parse(s)[0] for s in sentences_for_fix(bds, utc=_utc(bds))]
    assert not [t for t in talkers if t[:2] in ("GP", "GA")]
    assert talkers.count("GBGSA") == 1


def _systems(sky: dict) -> set[int]:
    """The gpsd GNSS IDs of a SKY message's satellites."""
    return {s["gnssid"] for s in sky["satellites"]}


@pytest.mark.needs("gpsd")
def test_gpsd_sees_every_system_and_the_used_satellites():
    """gpsd (an independent NMEA parser) reading our multi-system NMEA over TCP: TPV mode 3,
    and SKY lists GPS, Galileo and BeiDou satellites with ``used`` true exactly for the
    satellites in our GSAs."""
    base = _fixes()[0]
    server = NmeaTcpServer("127.0.0.1", 0)
    out = Publishers([server])
    tpv, sky = [], []
    try:
        with gpsd_watching(f"tcp://127.0.0.1:{server.address[1]}") as gpsd:
            deadline = time.monotonic() + HANG_S
            while server.n_clients != 1:
                assert time.monotonic() < deadline, "gpsd did not connect"
                time.sleep(0.002)
            for k in range(300):
                # gpsd reports a SKY per GSV group it has read: wait for one that holds
                # every system (a SKY of the first groups alone lacks the others)
                if len(tpv) >= 3 and any(_systems(m) >= {0, 2, 3} for m in sky):
                    break
                fix = dataclasses.replace(base, gpst_tow_s=base.gpst_tow_s + k)
                out.fix(fix, since_start_s=float(k))
                for msg in gpsd.messages(0.05):
                    if msg.get("class") == "TPV" and msg.get("mode") == 3:
                        tpv.append(msg)
                    elif msg.get("class") == "SKY" and msg.get("satellites"):
                        sky.append(msg)
    finally:
        out.close()
    assert len(tpv) >= 3 and sky
    whole = [m for m in sky if _systems(m) >= {0, 2, 3}]
    assert whole, [_systems(m) for m in sky]
    sats = whole[-1]["satellites"]
    used_by_gpsd = {(s["gnssid"], s["svid"]) for s in sats if s["used"]}
    in_gsas = {
        (EXPECTED[letter][3], n)
        for letter in EXPECTED
        for n in sorted(int(p[1:]) for p in base.used if p[0] == letter)[:GSA_MAX_SV]
    }
    assert used_by_gpsd == in_gsas
