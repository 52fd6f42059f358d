"""RINEX 3 readers cross-checked against georinex, an independent parser."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from drivers.rinex import RinexObsReader, merge_nav, read_nav
from service.core.errors import FramingError
from service.core.timebase import gpst_from_datetime
from tests.support.independent import georinex_bds_ephemerides
from tests.support.paths import DATA

OBS_FILES = [
    "hksc-2021/hksc1610.obs",
    "hksc-2021/20210610.klt1.ublox.f9p.obs",
    "hk-tst-urban-2019/COM3_190428_124409.obs",
    "hk-urban-3geo-2020/rover.obs",
    "hk-polyu-f9p-ubx-2024/gnss_log_2024_09_25_15_24_49.24o",
    "twtf-septentrio-2023/TWTF00TWN_R_20232490000_01D_30S_MO.rnx",
]
NAV_FILES = [
    "hksc-2021/hksc1610.nav",
    "hk-urban-3geo-2020/navigation_message.nav",
    "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
]
MAX_EPOCHS = 300


def _georinex_obs(path, code):
    import georinex

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = georinex.load(path, use="C", meas=[f"C{code}"])
    out = {}
    for t in ds.time.values[:MAX_EPOCHS]:
        import pandas as pd

        week, tow = gpst_from_datetime(pd.Timestamp(t).to_pydatetime())
        vals = ds.sel(time=t)[f"C{code}"]
        out[(week, round(tow, 3))] = {
            f"C{int(str(s)[1:]):02d}": float(v)
            for s, v in zip(vals.sv.values, vals.values, strict=True)
            if np.isfinite(v) and v > 0
        }
    return out


@pytest.mark.parametrize("name", OBS_FILES)
def test_obs_matches_georinex(name):
    path = DATA / name
    reader = RinexObsReader(path)
    ours = {}
    for i, ep in enumerate(reader):
        if i >= MAX_EPOCHS:
            break
        ours[(ep.gpst_week, round(ep.gpst_tow_s, 3))] = dict(
            zip(ep.prn, ep.pr_m.tolist(), strict=True)
        )
    ref = _georinex_obs(path, reader.header.bds_code)
    assert ours.keys() == ref.keys()
    n = 0
    for key, sats in ref.items():
        assert ours[key].keys() == sats.keys(), key
        for prn, pr in sats.items():
            assert abs(ours[key][prn] - pr) < 1e-3
            n += 1
    assert n > 0


def test_b1i_code_by_version():
    assert RinexObsReader(DATA / "hk-tst-urban-2019/COM3_190428_124409.obs").header.bds_code == "2I"
    h = RinexObsReader(DATA / "twtf-septentrio-2023/TWTF00TWN_R_20232490000_01D_30S_MO.rnx").header
    assert h.bds_code == "2I" and h.obs_types["C"][0] == "C2I"


def test_space_in_satellite_ids_and_3_geos():
    # hk-tst-urban-2019 writes "C 1"; the IDs come out as C01
    path = DATA / "hk-tst-urban-2019/COM3_190428_124409.obs"
    assert "C 1" in path.read_text()
    ids = {p for ep in RinexObsReader(path) for p in ep.prn}
    assert "C01" in ids and not any(" " in p for p in ids)
    geos = [
        tuple(p for p in ep.prn if p in ("C01", "C02", "C03", "C04", "C05"))
        for ep in RinexObsReader(DATA / "hk-urban-3geo-2020/rover.obs")
    ]
    assert len(geos) == 300 and set(geos) == {("C01", "C03", "C04")}


@pytest.mark.parametrize("name", NAV_FILES)
def test_nav_matches_georinex(name):
    path = DATA / name
    ours = read_nav(path)
    text = path.read_text()
    ref = [r for r in georinex_bds_ephemerides(path) if "_" not in r["prn"]]
    assert ref, "georinex found no BDS records"
    pairs = {
        "sqrtA": "sqrt_a_sqrt_m",
        "Eccentricity": "e",
        "Toe": "toe_sow_s",
        "M0": "m0_rad",
        "Io": "i0_rad",
        "Omega0": "omega0_rad",
        "omega": "omega_rad",
        "OmegaDot": "omega_dot_rad_s",
        "IDOT": "idot_rad_s",
        "DeltaN": "delta_n_rad_s",
        "Cuc": "cuc_rad",
        "Cus": "cus_rad",
        "Crc": "crc_m",
        "Crs": "crs_m",
        "Cic": "cic_rad",
        "Cis": "cis_rad",
        "SVclockBias": "af0_s",
        "SVclockDrift": "af1_s_s",
        "TGD1": "tgd1_s",
    }
    for rec in ref:
        cand = [e for e in ours.ephemerides[rec["prn"]] if e.toe_sow_s == rec["Toe"]]
        assert len(cand) == 1, rec["prn"]
        e = cand[0]
        for g, mine in pairs.items():
            assert math.isclose(getattr(e, mine), rec[g], rel_tol=1e-12, abs_tol=1e-20), (g, mine)
        assert e.week == int(rec["BDTWeek"])
        if (
            text.count(
                rec["prn"]
                + " "
                + str(rec["epoch"]).replace("-", " ").replace("T", " ").replace(":", " ")
            )
            == 1
        ):  # repeated sets: the latest transmission wins
            assert e.health == int(rec["SatH1"])


def test_bds_only_302_nav_literal_record():
    """georinex reads no BDS record from 3.02 BDS-only files; check one against its text:
    C01 2024 09 25 06:00:00, af0 9.253375465050D-04, af1 2.944311461306D-12."""
    nav = read_nav(DATA / "hk-polyu-f9p-ubx-2024/hksc269h.24f")
    c01 = min(nav.ephemerides["C01"], key=lambda e: e.toc_sow_s)
    assert c01.af0_s == 9.253375465050e-04 and c01.af1_s_s == 2.944311461306e-12
    assert c01.toc_sow_s == 3 * 86400 + 6 * 3600  # Wednesday 06:00 BDT
    assert len(nav.ephemerides) == 50 and nav.iono_bds is not None


def test_iono_headers_literal_values():
    nav = read_nav(DATA / "hksc-2021/hksc1610.nav")
    assert nav.iono_bds.alpha == (0.9313e-08, 0.4470e-07, -0.3576e-06, 0.5961e-06)
    assert nav.iono_bds.beta == (0.1188e06, 0.1638e06, -0.3277e06, 0.1966e06)
    assert nav.iono_gps.alpha[0] == 0.5588e-08 and nav.iono_bds.system == "BDS"
    only = read_nav(DATA / "hk-tst-urban-2019/hksc1180.19b")
    assert only.iono_bds.beta[3] == -7.4056e06 and only.iono_gps is None
    perth = read_nav(DATA / "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx")
    assert perth.iono_bds is None and perth.iono_gps.alpha[0] == 0.1024e-07
    both = merge_nav(perth, only)
    assert both.iono_bds == only.iono_bds and set(both.ephemerides) >= set(only.ephemerides)


def test_duplicate_records_are_kept_once_latest_transmission_wins():
    nav = read_nav(DATA / "hksc-2021/hksc1610.nav")
    toes = [e.toe_sow_s for e in nav.ephemerides["C01"]]
    assert len(toes) == len(set(toes))
    # PERT: C11 toe 370800 is sent at 370800 with SatH1 0, then again at 372210 with SatH1 1
    perth = read_nav(DATA / "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx")
    (c11,) = [e for e in perth.ephemerides["C11"] if e.toe_sow_s == 370800.0]
    assert c11.health == 1


def _broken_copy(tmp_path, src, lineno, new):
    lines = (DATA / src).read_text().splitlines(keepends=True)
    lines[lineno - 1] = new
    out = tmp_path / (DATA / src).name
    out.write_text("".join(lines))
    return out


def test_broken_epoch_line_names_file_and_line(tmp_path):
    src = "hksc-2021/hksc1610.obs"
    lines = (DATA / src).read_text().splitlines()
    epoch_lines = [i + 1 for i, line in enumerate(lines) if line.startswith(">")]
    target = epoch_lines[10]
    bad = _broken_copy(tmp_path, src, target, "> 2021 06 xx 03 36 04.0000000  0 30\n")
    with pytest.raises(FramingError) as exc:
        list(RinexObsReader(bad))
    assert f"{bad.name}:{target}:" in str(exc.value)
    # epochs before the damage were delivered
    got = []
    with pytest.raises(FramingError):
        for ep in RinexObsReader(bad):
            got.append(ep)
    assert len(got) == 10


def test_not_rinex3_and_no_end_of_header(tmp_path):
    v2 = tmp_path / "old.obs"
    v2.write_text(
        "     2.11           OBSERVATION DATA    M (MIXED)           RINEX VERSION / TYPE\n"
    )
    with pytest.raises(FramingError, match=r"not 3\.xx"):
        RinexObsReader(v2)
    cut = tmp_path / "cut.obs"
    cut.write_text("".join((DATA / OBS_FILES[0]).read_text().splitlines(keepends=True)[:10]))
    with pytest.raises(FramingError, match="no END OF HEADER"):
        RinexObsReader(cut)
    with pytest.raises(FramingError, match="not a RINEX file"):
        read_nav(DATA / "tiny-ubx-rtcm/pygpsdata-RXMRAWX.log")


def test_version_305_header_is_accepted(tmp_path):
    src = (DATA / "hksc-2021/hksc1610.obs").read_text().splitlines(keepends=True)
    src[0] = src[0].replace("3.04", "3.05", 1)
    p = tmp_path / "v305.obs"
    p.write_text("".join(src))
    eps = list(RinexObsReader(p))
    assert RinexObsReader(p).header.version == 3.05 and len(eps) == 205
