"""Velocity from Doppler on real recordings, through `bdsfix solve` (JSONL records).

- HKSC (Hong Kong SatRef, a static geodetic station, 205 epochs at 30 s): the true speed is
  0, so the reported speed over ground is its error: median <= 0.05 m/s, p95 <= 0.2 m/s.
- TST urban drive (Hong Kong, 2019, u-blox receiver in a car): the truth is the survey-grade
  track of groundTruth_TST.csv (GPS week, GPS time of week, latitude, longitude, height at
  1 Hz); its velocity is the difference of consecutive truth positions over their time
  step, at the middle of the step, interpolated linearly to each epoch. Over the epochs
  where the SPP solver fixes inside the truth's span, the error of the reported horizontal
  speed has median <= 0.5 m/s; an epoch with a fix and no velocity counts as an infinite
  error.
- The other drivers' Doppler signs: the static Hiroshima station through RTCM MSM7, and the
  PolyU UBX walk against the receiver's own NAV-PVT speed.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from service.commands.cli import main
from tests.support.fixes import ecef_m
from tests.support.independent import enu_rows
from tests.support.paths import DATA
from tests.system.test_replay_golden import CASES, _args

TST = DATA / "hk-tst-urban-2019"


def _solve(tmp_path, obs, nav, *extra) -> list[dict]:
    out = tmp_path / "fixes.jsonl"
    rc = main(["solve", str(obs), str(nav), "--out", str(out), *extra])
    assert rc == 0
    return [json.loads(line) for line in out.read_text().splitlines()]


def test_hksc_static_station_has_near_zero_speed(tmp_path):
    d = DATA / "hksc-2021"
    recs = _solve(tmp_path, d / "hksc1610.obs", d / "hksc1610.nav", "--mode", "both")
    fixes = [r for r in recs if r["mode"] != "none"]
    assert len(fixes) == 2 * 205
    with_v = [r for r in fixes if "speed_m_s" in r]
    assert len(with_v) == len(fixes)  # every fix has a velocity
    speed = np.array([r["speed_m_s"] for r in with_v])
    up = np.array([r["v_enu_m_s"][2] for r in with_v])
    assert np.median(speed) <= 0.05 and np.percentile(speed, 95) <= 0.2
    assert np.median(np.abs(up)) <= 0.1
    # the reported sigmas are of the size of the errors (neither 10x smaller nor larger)
    std = np.array([r["std_speed_m_s"] for r in with_v])
    assert 0.1 <= np.median(speed) / np.median(std) <= 10


def _truth_velocity():
    """Mid-step times [GPS s of week], ENU velocities [m/s] and whether each step is one
    second (a gap in the truth is not differenced across)."""
    rows = [[float(v) for v in r] for r in csv.reader((TST / "groundTruth_TST.csv").open())]
    t = np.array([r[1] for r in rows])
    x = np.array([ecef_m(r[2], r[3], r[4]) for r in rows])
    dt = np.diff(t)
    mid = (t[1:] + t[:-1]) / 2
    v = np.array(
        [enu_rows(rows[k][2], rows[k][3]) @ ((x[k + 1] - x[k]) / dt[k]) for k in range(len(dt))]
    )
    return mid, v, np.abs(dt - 1.0) < 1e-6


@pytest.mark.parametrize("mode", ["spp"])
def test_tst_urban_drive_speed_against_the_ground_truth(tmp_path, mode):
    recs = _solve(tmp_path, TST / "COM3_190428_124409.obs", TST / "hksc1180.19b", "--mode", mode)
    mid, v_true, one_s = _truth_velocity()
    errors = []
    true_speeds = []
    for r in recs:
        if r["mode"] != mode:
            continue
        t = r["gpst_tow_s"]
        if not mid[0] <= t <= mid[-1]:
            continue
        k = int(np.searchsorted(mid, t))
        if not (one_s[max(k - 1, 0)] and one_s[min(k, len(one_s) - 1)]):
            continue  # a gap in the truth around this epoch
        ve, vn = (float(np.interp(t, mid, v_true[:, j])) for j in range(2))
        true_speeds.append(math.hypot(ve, vn))
        if "speed_m_s" not in r:
            errors.append(math.inf)
            continue
        errors.append(abs(r["speed_m_s"] - math.hypot(ve, vn)))
    assert len(errors) >= 400  # the drive inside the truth's span
    assert np.median(true_speeds) > 2.0  # the car does move
    assert np.median(errors) <= 0.5


def _replay_fixes(tmp_path, case: str) -> list[dict]:
    out = tmp_path / "fixes.jsonl"
    rc = main(["replay", *_args(CASES[case].args), "--max-speed", "--jsonl-out", str(out)])
    assert rc == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    return [r for r in recs if r["class"] == "FIX" and r["mode"] != "none"]


def test_rtcm_msm_doppler_sign_static_hiroshima_station(tmp_path):
    """The RTCM driver's Doppler (MSM7 phase-range rate) through the stream path: the
    Hiroshima OEM729 is a static reference station (its 1005 ARP), so every speed is an
    error; with the rate's sign wrong the satellites' hundreds of m/s would remain."""
    fixes = _replay_fixes(tmp_path, "hiroshima-rtcm")
    speeds = [r["speed_m_s"] for r in fixes]
    assert len(speeds) == len(fixes) >= 40
    assert np.median(speeds) <= 0.05 and max(speeds) <= 0.2


def test_ubx_doppler_against_the_receivers_own_velocity(tmp_path):
    """The UBX driver's Doppler (RAWX doMes) on the PolyU ZED-F9P capture, a walk: the
    F9P's own NAV-PVT ground speed (its multi-GNSS solution, read here with pyubx2) is the
    reference; our BDS-only speed agrees with it to a median 0.5 m/s, and both move."""
    from pyubx2 import UBXReader

    capture = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
    ground: dict[int, float] = {}
    with capture.open("rb") as fh:
        for _raw, msg in UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is not None and msg.identity == "NAV-PVT":
                ground[round(msg.iTOW / 1000)] = msg.gSpeed / 1000.0  # mm/s
    fixes = _replay_fixes(tmp_path, "polyu-f9p-ubx")
    pairs = [
        (r["speed_m_s"], ground[round(r["gpst_tow_s"])])
        for r in fixes
        if "speed_m_s" in r and round(r["gpst_tow_s"]) in ground
    ]
    assert len(pairs) >= 150
    ours, theirs = np.array(pairs).T
    assert np.median(theirs) > 0.8  # walking
    assert np.median(np.abs(ours - theirs)) <= 0.5
