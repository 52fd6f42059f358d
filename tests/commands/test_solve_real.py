"""`bdsfix solve` on real recordings: the fast fix against SPP and the surveyed truth."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest

from service.commands.cli import main
from tests.support.independent import HKSC_TRUTH_ECEF_M
from tests.support.paths import DATA

FIELDS_ALWAYS = {"class", "solver", "mode", "gpst_week", "gpst_tow_s", "n_full", "n_frac"}
FIELDS_FIX = {"x_ecef_m", "lat_deg", "lon_deg", "alt_m", "clock_bias_m", "pdop", "resid_rms_m"}


def _solve(tmp_path, obs, nav, *extra):
    out = tmp_path / "fixes.jsonl"
    rc = main(["solve", str(obs), *[str(n) for n in nav], "--out", str(out), *extra])
    assert rc == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    by_epoch: dict[float, dict[str, dict]] = defaultdict(dict)
    for r in recs:
        by_epoch[(r["gpst_week"], r["gpst_tow_s"])][r["solver"]] = r
    return recs, by_epoch


@pytest.fixture(scope="module")
def hksc(tmp_path_factory):
    d = DATA / "hksc-2021"
    return _solve(
        tmp_path_factory.mktemp("hksc"), d / "hksc1610.obs", [d / "hksc1610.nav"], "--mode", "both"
    )


def test_hksc_fast_fix_at_every_spp_epoch_and_identical(hksc):
    _, by_epoch = hksc
    assert len(by_epoch) == 205
    spp_epochs = [k for k, v in by_epoch.items() if v["spp"]["mode"] == "spp"]
    assert len(spp_epochs) == 205
    worst = 0.0
    for k in spp_epochs:
        fast, spp = by_epoch[k]["fast"], by_epoch[k]["spp"]
        assert fast["mode"] == "fast", fast.get("reason")
        assert fast["n_full"] == 5 and fast["n_frac"] >= 1
        worst = max(worst, float(np.linalg.norm(np.subtract(fast["x_ecef_m"], spp["x_ecef_m"]))))
    assert worst <= 1e-3


def test_hksc_spp_accuracy_against_the_surveyed_station(hksc):
    _, by_epoch = hksc
    err = [
        np.linalg.norm(np.subtract(v["spp"]["x_ecef_m"], HKSC_TRUTH_ECEF_M))
        for v in by_epoch.values()
    ]
    rms = float(np.sqrt(np.mean(np.square(err))))
    assert rms <= 2.1, rms


def test_hksc_records_follow_the_contract(hksc):
    recs, _ = hksc
    for r in recs:
        assert r.keys() >= FIELDS_ALWAYS
        assert None not in r.values()
        assert r["class"] == "FIX"
        if r["mode"] != "none":
            assert r.keys() >= FIELDS_FIX
        if r["solver"] == "fast" and r["mode"] == "fast":
            assert {"gdop_full", "ambiguity"} <= r.keys()
            assert len(r["ambiguity"]) == r["n_frac"]
            assert 50 < r["gdop_full"] < 3000


def test_hksc_recovered_ambiguities_are_exact(hksc):
    """Every recovered N equals floor(P / cT) of the full pseudorange in the file, T the
    code period: 1 ms for BeiDou B1I and GPS C/A, 4 ms for Galileo E1 (every system by
    default)."""
    from drivers.rinex import RinexObsReader

    _, by_epoch = hksc
    c_m_s = 299_792_458.0
    period_s = {"C": 1e-3, "G": 1e-3, "E": 4e-3}
    n_checked = dict.fromkeys(period_s, 0)
    for ep in RinexObsReader(DATA / "hksc-2021" / "hksc1610.obs", systems=period_s):
        fast = by_epoch[(ep.gpst_week, ep.gpst_tow_s)]["fast"]
        for prn, n in fast["ambiguity"].items():
            pr = float(ep.pr_m[ep.prn.index(prn)])
            assert n == int(pr // (c_m_s * period_s[prn[0]])), prn
            n_checked[prn[0]] += 1
    assert n_checked["C"] > 2000 and n_checked["G"] > 1000 and n_checked["E"] > 500, n_checked


def test_three_geos_the_fast_solver_takes_the_coarse_time_fix_spp_fixes(tmp_path):
    """Three GEOs: too few full ranges for the paper's method at every epoch, so the fast
    solver's fix is the coarse-time fix (as the stream's; before, each was declined
    ``too_few_full``); SPP of the full ranges fixes nearly every epoch."""
    d = DATA / "hk-urban-3geo-2020"
    _, by_epoch = _solve(
        tmp_path, d / "rover.obs", [d / "navigation_message.nav"], "--mode", "both"
    )
    assert len(by_epoch) == 300
    n_spp = 0
    for v in by_epoch.values():
        assert v["fast"]["mode"] == "fast" and v["fast"]["method"] == "coarse_time"
        n_spp += v["spp"]["mode"] == "spp"
    assert n_spp >= 290


def test_urban_moving_no_crash_fast_equals_spp_where_gated(tmp_path):
    d = DATA / "hk-tst-urban-2019"
    _, by_epoch = _solve(
        tmp_path, d / "COM3_190428_124409.obs", [d / "hksc1180.19b"], "--mode", "both"
    )
    assert len(by_epoch) == 1760
    n_fast = n_decline = n_other_subset = n_relative = 0
    for v in by_epoch.values():
        fast, spp = v["fast"], v["spp"]
        if fast["mode"] == "fast" and not fast.get("ambiguity"):
            # a coarse-time fix with every range fractional and the millisecond common to
            # them in doubt: the coarse-time solution itself, not SPP (coarse.py step 5),
            # within its protection level of SPP's position
            n_relative += 1
            assert fast["method"] == "coarse_time"
            if spp["mode"] == "spp":
                apart_m = np.linalg.norm(np.subtract(fast["x_ecef_m"], spp["x_ecef_m"]))
                assert apart_m <= fast["hpl_m"]
        elif fast["mode"] == "fast":
            n_fast += 1
            if spp["mode"] == "spp" and set(fast.get("excluded", ())) == set(
                spp.get("excluded", ())
            ):
                assert np.linalg.norm(np.subtract(fast["x_ecef_m"], spp["x_ecef_m"])) <= 1e-3
            else:
                # fault exclusion left the two solvers different satellites (the fast fix
                # cannot drop a GEO it needs as one of its four full measurements)
                n_other_subset += 1
                assert fast.get("excluded") or spp.get("excluded") or spp["mode"] == "none"
        else:
            n_decline += 1
            assert fast["reason"]
    assert n_decline > 0
    assert n_other_subset <= 0.05 * n_fast
    assert n_relative <= 0.05 * n_fast
    print(
        f"hk-tst-urban: {n_fast} fast fixes, {n_decline} declines, {n_other_subset} other "
        f"subset, {n_relative} coarse-time solutions"
    )


def _with_flag_7(tmp_path, index):
    """hksc1610.obs with the epoch line of epoch ``index`` given flag 7 (not in RINEX 3)."""
    lines = (DATA / "hksc-2021" / "hksc1610.obs").read_text().splitlines(keepends=True)
    at = [k for k, line in enumerate(lines) if line.startswith(">")][index]
    assert lines[at][31] == "0"
    lines[at] = lines[at][:31] + "7" + lines[at][32:]
    path = tmp_path / "hksc1610.obs"
    path.write_text("".join(lines))
    return path, at + 1


def test_solve_and_replay_skip_an_epoch_with_an_unknown_flag_alike(tmp_path, capsys, caplog):
    # 205 epochs; the 51st (after 50 good ones) gets flag 7: both commands skip that epoch
    # with a warning naming file:line and solve the other 204
    obs, lineno = _with_flag_7(tmp_path, 50)
    nav = DATA / "hksc-2021" / "hksc1610.nav"
    _, by_epoch = _solve(tmp_path, obs, [nav], "--mode", "both")
    assert len(by_epoch) == 204
    assert f"hksc1610.obs:{lineno}: epoch flag 7" in caplog.text
    assert "skipped input: epochs_skipped 1" in capsys.readouterr().err
    caplog.clear()
    out = tmp_path / "replay.jsonl"
    rc = main(["replay", str(obs), "--nav", str(nav), "--max-speed", "--jsonl-out", str(out)])
    assert rc == 0
    replayed = {
        (r["gpst_week"], r["gpst_tow_s"])
        for r in map(json.loads, out.read_text().splitlines())
        if r.get("class") == "FIX"
    }
    assert replayed == set(by_epoch)
    assert f"hksc1610.obs:{lineno}: epoch flag 7" in caplog.text


def test_default_pdop_mask_is_u_blox_25_on_the_f9p_rover(tmp_path):
    # the F9P rover (no GEOs) has SPP epochs with PDOP between 10 and 25 with BeiDou alone
    # (with GPS and Galileo too its PDOP stays below 10): the default mask (u-blox's 25)
    # publishes them and still declines none at or below it
    d = DATA / "hksc-2021"
    obs, nav = d / "20210610.klt1.ublox.f9p.obs", [d / "hksc1610.nav"]
    recs, _ = _solve(tmp_path, obs, nav, "--systems", "C")
    spp = [r for r in recs if r["solver"] == "spp" and r["mode"] == "spp"]
    pdops = [r["pdop"] for r in spp]
    assert any(10.0 < p <= 25.0 for p in pdops)
    assert max(pdops) <= 25.0


@pytest.mark.parametrize("systems", ["G", "G,E"])
def test_a_selection_without_beidou_solves_from_the_systems_selected(tmp_path, systems):
    """``--systems G`` (or ``G,E``) takes its ephemerides from the nav file's GPS (and
    Galileo) sets: the file is not refused for want of a BeiDou set, every epoch fixes near
    the station's surveyed position, and a fix of several systems names only those
    selected."""
    d = DATA / "hksc-2021"
    out = tmp_path / "fixes.jsonl"
    args = ["solve", str(d / "hksc1610.obs"), str(d / "hksc1610.nav"), "--mode", "spp"]
    assert main([*args, "--systems", systems, "--out", str(out)]) == 0
    fixes = [r for r in map(json.loads, out.read_text().splitlines()) if r["class"] == "FIX"]
    spp = [f for f in fixes if f["mode"] == "spp"]
    assert len(spp) == 205
    err_m = [np.linalg.norm(np.array(f["x_ecef_m"]) - HKSC_TRUTH_ECEF_M) for f in spp]
    assert max(err_m) < 10.0
    assert all(set(f.get("used_by_system", {})) <= set(systems.split(",")) for f in spp)
