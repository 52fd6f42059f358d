"""Independent references for cross-checks: georinex-parsed ephemerides and a scalar,
line-by-line transcription of the ICD B1I 5.2.4.12 user algorithm."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from service.core.types import Ephemeris

HKSC_TRUTH_ECEF_M = np.array([-2414266.9197, 5386768.9868, 2407460.0314])


def georinex_bds_ephemerides(path: Path) -> list[dict[str, float]]:
    """Every BDS record of a RINEX 3 nav file as a dict of floats, parsed by georinex."""
    return georinex_ephemerides(path, "C")


def georinex_ephemerides(path: Path, system: str) -> list[dict[str, float]]:
    """Every record of one system (RINEX 3 letter) of a nav file as a dict of floats, parsed
    by georinex (repeated records come as ``"G05_1"`` ...: callers keep what they need)."""
    import georinex

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nav = georinex.load(path, use=system)
    out = []
    for sv in nav.sv.values:
        ds = nav.sel(sv=sv)
        for t in ds.time.values:
            rec = ds.sel(time=t)
            if not np.isfinite(float(rec["sqrtA"])):
                continue
            row = {k: float(rec[k]) for k in rec.data_vars}
            row["prn"] = str(sv)
            row["epoch"] = np.datetime64(t, "s")
            out.append(row)
    return out


def icd_position(
    rec: dict,
    t_bdt_sow: float,
    geo: bool,
    gm: float = 3.986004418e14,
    we: float = 7.2921150e-5,
) -> tuple[float, float, float]:
    """ECEF position from one georinex record, per ICD B1I Table 5-11, in plain scalars.

    With ``geo`` False this is also IS-GPS-200 Table 20-IV and the Galileo OS SIS ICD 5.1.1
    algorithm, given that system's ``gm`` and ``we`` (the defaults are CGCS2000's) and a
    time in the record's own time scale."""
    a = rec["sqrtA"] ** 2
    tk = t_bdt_sow - rec["Toe"]
    if tk > 302400:
        tk -= 604800
    if tk < -302400:
        tk += 604800
    n = math.sqrt(gm / a**3) + rec["DeltaN"]
    m = rec["M0"] + n * tk
    e_anom = m
    for _ in range(30):
        e_anom = m + rec["Eccentricity"] * math.sin(e_anom)
    ecc = rec["Eccentricity"]
    v = math.atan2(math.sqrt(1 - ecc * ecc) * math.sin(e_anom), math.cos(e_anom) - ecc)
    phi = v + rec["omega"]
    du = rec["Cus"] * math.sin(2 * phi) + rec["Cuc"] * math.cos(2 * phi)
    dr = rec["Crs"] * math.sin(2 * phi) + rec["Crc"] * math.cos(2 * phi)
    di = rec["Cis"] * math.sin(2 * phi) + rec["Cic"] * math.cos(2 * phi)
    u = phi + du
    r = a * (1 - ecc * math.cos(e_anom)) + dr
    i = rec["Io"] + rec["IDOT"] * tk + di
    xo, yo = r * math.cos(u), r * math.sin(u)
    if geo:
        om = rec["Omega0"] + rec["OmegaDot"] * tk - we * rec["Toe"]
    else:
        om = rec["Omega0"] + (rec["OmegaDot"] - we) * tk - we * rec["Toe"]
    x = xo * math.cos(om) - yo * math.cos(i) * math.sin(om)
    y = xo * math.sin(om) + yo * math.cos(i) * math.cos(om)
    z = yo * math.sin(i)
    if not geo:
        return x, y, z
    f = math.radians(-5.0)
    rx = np.array([[1, 0, 0], [0, math.cos(f), math.sin(f)], [0, -math.sin(f), math.cos(f)]])
    p = we * tk
    rz = np.array([[math.cos(p), math.sin(p), 0], [-math.sin(p), math.cos(p), 0], [0, 0, 1]])
    out = rz @ rx @ np.array([x, y, z])
    return float(out[0]), float(out[1]), float(out[2])


def _kepler_fields(rec: dict) -> dict[str, float]:
    """The clock and Keplerian fields every georinex record maps the same way (field mapping
    only): t_oc is the record's epoch as seconds of its week."""
    sod = (rec["epoch"] - rec["epoch"].astype("datetime64[D]")).astype(int)
    dow = (rec["epoch"].astype("datetime64[D]").astype(int) - 3) % 7  # 1970-01-01 was Thu
    return {
        "toe_sow_s": rec["Toe"],
        "toc_sow_s": float(dow * 86400 + sod),
        "af0_s": rec["SVclockBias"],
        "af1_s_s": rec["SVclockDrift"],
        "af2_s_s2": rec["SVclockDriftRate"],
        "sqrt_a_sqrt_m": rec["sqrtA"],
        "e": rec["Eccentricity"],
        "i0_rad": rec["Io"],
        "omega0_rad": rec["Omega0"],
        "omega_rad": rec["omega"],
        "m0_rad": rec["M0"],
        "delta_n_rad_s": rec["DeltaN"],
        "omega_dot_rad_s": rec["OmegaDot"],
        "idot_rad_s": rec["IDOT"],
        "cuc_rad": rec["Cuc"],
        "cus_rad": rec["Cus"],
        "crc_m": rec["Crc"],
        "crs_m": rec["Crs"],
        "cic_rad": rec["Cic"],
        "cis_rad": rec["Cis"],
    }


def eph_from_georinex(rec: dict) -> Ephemeris:
    """Map a georinex record to our type (field mapping only, no computation)."""
    return Ephemeris(
        prn=rec["prn"],
        week=int(rec["BDTWeek"]),
        **_kepler_fields(rec),
        tgd1_s=rec["TGD1"],
        health=int(rec["SatH1"]),
    )


BDT_BEHIND_GPST_S = 14.0
BDT_WEEKS_AFTER_GPST = 1356
"""BDT = GPST - 14 s, BDT week 0 = GPS week 1356 (BDS-SIS-ICD-B1I-3.0 4.2), written here from
the ICD (not taken from service.core.timebase)."""


def eph_from_georinex_gps_like(rec: dict) -> Ephemeris:
    """Map a georinex GPS or Galileo record to our type (field mapping, then the times put
    on BDT as :class:`service.core.types.Ephemeris` holds every set): the week is GPSWeek or
    GALWeek (RINEX 3 continues the GPS week count for both), t_oc the record's epoch, health
    the system's health field and the group delay TGD (GPS) or BGD E1/E5b (Galileo). A set
    whose t_oe or t_oc is within 14 s of its week's start is not expected here (the test
    files have none: asserted)."""
    week = rec.get("GPSWeek", rec.get("GALWeek"))
    fields = _kepler_fields(rec)
    assert fields["toe_sow_s"] >= BDT_BEHIND_GPST_S and fields["toc_sow_s"] >= BDT_BEHIND_GPST_S
    fields["toe_sow_s"] -= BDT_BEHIND_GPST_S
    fields["toc_sow_s"] -= BDT_BEHIND_GPST_S
    return Ephemeris(
        prn=rec["prn"],
        week=int(week) - BDT_WEEKS_AFTER_GPST,
        **fields,
        tgd1_s=rec.get("TGD", rec.get("BGDe5b", 0.0)),
        health=int(rec["health"]),
        source="georinex",
    )


def enu_rows(lat_deg: float, lon_deg: float) -> np.ndarray:
    """East, north, up unit vectors in ECEF (rows), written here for the tests."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    return np.array(
        [
            [-math.sin(lo), math.cos(lo), 0.0],
            [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
            [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)],
        ]
    )
