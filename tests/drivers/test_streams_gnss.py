"""GPS and Galileo from receiver streams (issue 19): RTCM 3 MSM7 1077/1097 rows and 1019/1046
ephemerides of the Hiroshima OEM729 stream (../shared/data/hiroshima-oem729-rtcm-2022), fixed
against the stream's own 1005 antenna reference point; UBX RXM-RAWX GPS rows of the PolyU F9P
capture against the receiver's own NAV-PVT.

References: pyrtcm's parse of the same frames (counts, fields), the scalar transcription of
IS-GPS-200 Table 20-IV / Galileo OS SIS ICD 5.1.1 (tests/support/independent.py) for the
orbits, and the surveyed ARP.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from pyrtcm import RTCMReader

from drivers.source import open_source
from service.core.ephemeris import EphemerisStore
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.types import Ephemeris, MeasurementEpoch
from service.engine.solver import SolverConfig, solve
from tests.support.independent import BDT_BEHIND_GPST_S, icd_position
from tests.support.paths import DATA

RTCM = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
ARP_ECEF_M = np.array([-3551876.8287, 3887786.8598, 3586946.3873])  # its 1005 message
PI = 3.1415926535898  # IS-GPS-200 20.3.3.4.3, Galileo OS SIS ICD 5.1.1
ICD = {"G": (3.986005e14, 7.2921151467e-5), "E": (3.986004418e14, 7.2921151467e-5)}


@functools.cache
def _messages() -> dict[str, list]:
    out: dict[str, list] = {}
    with open(RTCM, "rb") as fh:
        for _, msg in RTCMReader(fh):
            if msg is not None:
                out.setdefault(str(msg.identity), []).append(msg)
    return out


@functools.cache
def _events(systems: str) -> tuple[list[Ephemeris], list[MeasurementEpoch]]:
    ephs, epochs = [], []
    with open_source(str(RTCM), systems=frozenset(systems)) as src:
        for ev in src:
            if isinstance(ev, Ephemeris):
                ephs.append(ev)
            elif isinstance(ev, MeasurementEpoch):
                epochs.append(ev)
    return ephs, epochs


def test_default_stream_keeps_beidou_alone():
    ephs, epochs = _events("C")
    assert {e.prn[0] for e in ephs} == {"C"}
    assert all({p[0] for p in ep.prn} <= {"C"} for ep in epochs)


def test_gps_and_galileo_ephemerides_and_rows():
    """Every 1019 and 1046 becomes a set of its satellite (pyrtcm's DF009 / DF252); the
    epochs carry GPS L1 C/A (1C) and Galileo E1 (1C) rows beside B1I."""
    ephs, epochs = _events("CGE")
    msgs = _messages()
    gps = {f"G{int(m.DF009):02d}" for m in msgs["1019"]}
    gal = {f"E{int(m.DF252):02d}" for m in msgs["1046"]}
    assert {e.prn for e in ephs if e.prn[0] == "G"} == gps and len(gps) >= 8
    assert {e.prn for e in ephs if e.prn[0] == "E"} == gal and len(gal) >= 6
    rows = [(p, s) for ep in epochs for p, s in zip(ep.prn, ep.signal, strict=True)]
    assert {s for p, s in rows if p[0] in "GE"} == {"1C"}
    assert {p[0] for p, _ in rows} == {"C", "G", "E"}


def test_ephemeris_orbits_equal_the_icd_transcription_of_the_message():
    """Each GPS/Galileo set mapped, evaluated on BDT at t_oe + 10 min, equals the scalar ICD
    transcription of the pyrtcm fields (semicircles times pi, here) at the same GPST/GST
    instant to 1 mm."""
    ephs, _ = _events("CGE")
    msgs = _messages()
    worst, n = 0.0, 0
    for number, sys_letter, num_df, names in (
        ("1019", "G", "DF009", _1019),
        ("1046", "E", "DF252", _1046),
    ):
        for m in msgs[number]:
            rec = {
                k: float(getattr(m, df)) * (PI if semi else 1.0) for k, (df, semi) in names.items()
            }
            prn = f"{sys_letter}{int(getattr(m, num_df)):02d}"
            eph = next(e for e in ephs if e.prn == prn and e.sqrt_a_sqrt_m == rec["sqrtA"])
            t = rec["Toe"] + 600.0
            pos, _ = sat_pos_clock(
                EphemerisArrays.from_ephemerides([eph]), eph.week, np.array([t - BDT_BEHIND_GPST_S])
            )
            ref = icd_position(rec, t, False, *ICD[sys_letter])
            worst = max(worst, float(np.linalg.norm(pos[0] - np.array(ref))))
            n += 1
    assert n >= 14 and worst < 1e-3, (n, worst)


def test_spp_with_every_system_of_the_stream_near_the_arp():
    """SPP on the stream's epochs with its own ephemerides (no ionosphere coefficients in the
    stream: unmodelled, counted as error): every epoch with a week fixes, with BeiDou, GPS and
    Galileo rows and a clock each, within 12 m of the ARP (measured 6.4-9.6 m; BeiDou
    alone 5.3-5.7 m, the difference mostly height: the unmodelled ionosphere)."""
    ephs, epochs = _events("CGE")
    store = EphemerisStore()
    store.add_all(ephs)
    fixes = [solve(ep, store, cfg=SolverConfig(), solver="spp") for ep in epochs if ep.week_known]
    ok = [f for f in fixes if f.ok]
    assert len(ok) == len(fixes) >= 40
    err = [float(np.linalg.norm(np.subtract(f.x_ecef_m, ARP_ECEF_M))) for f in ok]
    assert max(err) < 12.0, max(err)
    assert all(set(f.clocks_m) == {"C", "G", "E"} for f in ok)
    assert math.isfinite(sum(err))


_KEPLER = {
    "sqrtA": False, "Eccentricity": False, "Io": True, "Omega0": True, "omega": True,
    "M0": True, "DeltaN": True, "OmegaDot": True, "IDOT": True, "Cuc": False, "Cus": False,
    "Crc": False, "Crs": False, "Cic": False, "Cis": False, "Toe": False,
}  # fmt: skip
_1019 = dict(
    zip(
        _KEPLER,
        zip(
            ("DF092", "DF090", "DF097", "DF095", "DF099", "DF088", "DF087", "DF100", "DF079",
             "DF089", "DF091", "DF098", "DF086", "DF094", "DF096", "DF093"),
            _KEPLER.values(),
            strict=True,
        ),
        strict=True,
    )
)  # fmt: skip
_1046 = dict(
    zip(
        _KEPLER,
        zip(
            ("DF303", "DF301", "DF308", "DF306", "DF310", "DF299", "DF298", "DF311", "DF292",
             "DF300", "DF302", "DF309", "DF297", "DF305", "DF307", "DF304"),
            _KEPLER.values(),
            strict=True,
        ),
        strict=True,
    )
)  # fmt: skip


def test_ubx_rawx_gps_rows_fix_near_the_receivers_own_solution():
    """UBX RXM-RAWX of the PolyU F9P capture with --systems C,G semantics: GPS L1 C/A rows
    (gnssId 0, sigId 0) beside B1I, with the GPS and BDS nav files of the day: every epoch
    an SPP fix using both systems, within 30 m of the receiver's own NAV-PVT (pyubx2's
    parse; measured p50 8.2 m, max 24.8 m; BeiDou alone p50 4.7 m, max 14.4 m)."""
    from pyubx2 import UBXReader

    from service.commands.solve import load_navigation
    from service.core.geometry import geodetic_to_ecef

    d = DATA / "hk-polyu-f9p-ubx-2024"
    capture = d / "COM18___9600_240925_072456.ubx"
    pvt = {}
    with open(capture, "rb") as fh:
        for _, msg in UBXReader(fh, quitonerror=0):
            if msg is not None and getattr(msg, "identity", "") == "NAV-PVT":
                llh = (math.radians(msg.lat), math.radians(msg.lon), msg.height / 1000.0)
                pvt[round(msg.iTOW / 1000) % 604800] = geodetic_to_ecef(*llh)
    store, iono = load_navigation([str(d / "hksc269h.24f"), str(d / "hksc269h.24n")], systems="CG")
    with open_source(str(capture), systems=frozenset("CG")) as src:
        epochs = [ev for ev in src if isinstance(ev, MeasurementEpoch)]
    assert len(epochs) == 196
    assert all({p[0] for p in ep.prn} == {"C", "G"} for ep in epochs)
    fixes = [solve(ep, store, iono, SolverConfig(), "spp") for ep in epochs]
    assert all(f.ok and set(f.clocks_m) == {"C", "G"} for f in fixes)
    err = [np.linalg.norm(np.subtract(f.x_ecef_m, pvt[round(f.gpst_tow_s)])) for f in fixes]
    assert max(err) < 30.0, max(err)
