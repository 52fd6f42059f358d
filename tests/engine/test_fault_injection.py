"""Faults injected into the real HKSC recording (5 GEOs): every 4th epoch, one GEO or one
non-GEO (the satellite rotates through the epoch's GEOs / non-GEOs) carries a range error of
30 m to 150 km or exactly 1 ms; also two satellites at once.

The reference is the clean run's SPP fix of the same epoch (the engine on unfaulted data),
so what is measured is what the fault did. Every published fix, fast or SPP, must lie within
its own protection levels of it; from 100 m on, within 30 m; from 300 m on, >= 99 % of the
faulted epochs still publish, with the faulty satellite excluded. A 1 ms fault on a
fractional row changes nothing the fast solver sees (the fraction is the range modulo 1 ms):
its fix is the clean one and only the recovered integer moves by one; the stream test below
shows the later D1 SOW catches it.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.core.types import Fix, MeasurementEpoch
from service.engine.solver import fractionalize, solve_many
from tests.support.independent import HKSC_TRUTH_ECEF_M
from tests.support.paths import DATA, ROOT

HK = DATA / "hksc-2021"
MS_M = C_M_S * 1e-3
MAGNITUDES_M = (30.0, 100.0, 300.0, 1e3, 3e3, 150e3, MS_M)


@pytest.fixture(scope="module")
def hksc():
    store, iono = load_navigation([str(HK / "hksc1610.nav")])
    epochs = list(RinexObsReader(HK / "hksc1610.obs"))
    fast = solve_many([fractionalize(ep) for ep in epochs], store, iono, solver="fast")
    clean = list(zip(fast, solve_many(epochs, store, iono, solver="spp"), strict=True))
    return store, iono, epochs, clean


def _faulted(ep: MeasurementEpoch, faults: dict[str, float]) -> MeasurementEpoch:
    pr = ep.pr_m.copy()
    for prn, d in faults.items():
        pr[ep.prn.index(prn)] += d
    return replace(ep, pr_m=pr, frac_pr_m=np.mod(pr, MS_M))


def _pick(ep: MeasurementEpoch, k: int, geo: bool) -> str:
    sats = sorted(p for p in ep.prn if is_geo(p) == geo and math.isfinite(ep.pr_m[ep.prn.index(p)]))
    return sats[(k // 4) % len(sats)]


def _offset(fix: Fix, ref: Fix) -> tuple[float, float, float]:
    """Horizontal, vertical and 3D distance [m] of ``fix`` from ``ref``."""
    lat, lon, _ = ecef_to_geodetic(np.asarray(ref.x_ecef_m))
    d = np.subtract(fix.x_ecef_m, ref.x_ecef_m)
    e = enu_rotation(lat, lon) @ d
    return math.hypot(e[0], e[1]), abs(e[2]), float(np.linalg.norm(d))


def test_clean_run_is_unchanged_by_integrity(hksc):
    _, _, epochs, clean = hksc
    assert all(f.mode == "fast" and s.mode == "spp" for f, s in clean)
    worst = max(float(np.linalg.norm(np.subtract(f.x_ecef_m, s.x_ecef_m))) for f, s in clean)
    assert worst <= 1e-3
    err = [np.linalg.norm(np.subtract(s.x_ecef_m, HKSC_TRUTH_ECEF_M)) for _, s in clean]
    assert float(np.sqrt(np.mean(np.square(err)))) <= 2.1
    false = sum(bool(f.excluded) + bool(s.excluded) for f, s in clean)
    assert false <= 0.005 * 2 * len(epochs)
    assert all(s.chi2 is not None and math.isfinite(s.hpl_m) for _, s in clean)


def _run(hksc, faults_of):
    """Solve every faulted epoch (k % 4 == 0) with both solvers (in one batch each); the
    published fixes are checked against the clean SPP and returned with the faults."""
    store, iono, epochs, clean = hksc
    ks = range(0, len(epochs), 4)
    faults = [faults_of(epochs[k], k) for k in ks]
    bad = [_faulted(epochs[k], f) for k, f in zip(ks, faults, strict=True)]
    fast = solve_many([fractionalize(b) for b in bad], store, iono, solver="fast")
    spp = solve_many(bad, store, iono, solver="spp")
    out = []
    for k, faults_k, pair in zip(ks, faults, zip(fast, spp, strict=True), strict=True):
        ref = clean[k][1]
        for fix in pair:
            if fix.ok:
                h, v, _ = _offset(fix, ref)
                assert h <= fix.hpl_m and v <= fix.vpl_m, (k, faults_k, fix.solver, h, v, fix)
            out.append((k, faults_k, fix))
    return out


@pytest.mark.parametrize("geo", [True, False], ids=["GEO", "non-GEO"])
@pytest.mark.parametrize("magnitude_m", MAGNITUDES_M, ids=lambda m: f"{m:g}m")
def test_one_faulty_satellite(hksc, geo, magnitude_m):
    results = _run(hksc, lambda ep, k: {_pick(ep, k, geo): magnitude_m * (-1) ** (k // 4)})
    clean = hksc[3]
    for solver in ("fast", "spp"):
        mine = [(k, f, fix) for k, f, fix in results if fix.solver == solver]
        published = [(k, f, fix) for k, f, fix in mine if fix.ok]
        invisible = solver == "fast" and not geo and magnitude_m == MS_M
        if invisible:
            # the fraction is unchanged: the clean fix, the clean integers, so the recovered
            # range is the true one and misses the (faulty) full range by 1 ms
            epochs = hksc[2]
            for k, faults, fix in published:
                ((prn, d),) = faults.items()
                ref = clean[k][0]
                assert np.linalg.norm(np.subtract(fix.x_ecef_m, ref.x_ecef_m)) <= 1e-6
                assert fix.ambiguity == ref.ambiguity and not fix.excluded
                full_m = epochs[k].pr_m[epochs[k].prn.index(prn)] + d
                assert abs(abs(full_m - fix.recovered_pr_m[prn]) - MS_M) < 1.0
            assert len(published) == len(mine)
            continue
        if magnitude_m >= 100.0:
            for k, faults, fix in published:
                assert _offset(fix, clean[k][1])[2] <= 30.0, (k, faults, fix.excluded)
        if magnitude_m >= 300.0:
            assert len(published) >= 0.99 * len(mine), (solver, [f.reason for *_, f in mine])
            for k, faults, fix in published:
                (prn,) = faults
                assert prn in fix.excluded and prn not in fix.used, (k, faults, fix.excluded)


@pytest.mark.parametrize(
    "magnitudes_m", [(100.0, 300.0), (1e3, 3e3), (3e3, 150e3)], ids=lambda m: f"{m[0]:g}+{m[1]:g}m"
)
def test_two_faulty_satellites(hksc, magnitudes_m):
    def faults(ep, k):
        return {_pick(ep, k, True): magnitudes_m[0], _pick(ep, k, False): -magnitudes_m[1]}

    results = _run(hksc, faults)
    clean = hksc[3]
    published = [(k, f, fix) for k, f, fix in results if fix.ok]
    assert published  # FDE with two exclusions keeps fixes coming
    for k, faults_k, fix in published:
        assert _offset(fix, clean[k][1])[2] <= 30.0, (k, faults_k, fix.excluded)


def _rinex_with_fault(src: Path, dst: Path, prn: str, d_m: float) -> None:
    """A copy of a RINEX 3 obs file with ``d_m`` added to the first observable (C2I) of
    ``prn`` in every epoch (F14.3 in columns 4-17 of its record)."""
    out = []
    with open(src, encoding="ascii") as f:
        in_header = True
        for line in f:
            if in_header:
                in_header = "END OF HEADER" not in line
            elif line.startswith(prn) and line[3:17].strip():
                line = f"{line[:3]}{float(line[3:17]) + d_m:14.3f}{line[17:]}"
            out.append(line)
    dst.write_text("".join(out), encoding="ascii")


def test_a_1ms_fault_on_a_fractional_row_is_caught_at_the_d1_sow(tmp_path):
    """In a stream the fast fix resolves the faulty non-GEO's integer from geometry, so its
    recovered range is the true one; once that satellite's SOW decodes, the full (faulty)
    range disagrees by 1 ms: the D1 SOW check counts an integrity failure, and from then on
    SPP excludes the satellite."""
    obs = tmp_path / "hksc-c08-1ms.obs"
    _rinex_with_fault(HK / "hksc1610.obs", obs, "C08", MS_M)
    res = subprocess.run(
        [
            sys.executable, "-m", "service", "replay", str(obs), "--nav",
            str(HK / "hksc1610.nav"), "--restart-at", "60", "--max-speed", "--nmea-out",
            "/dev/null",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    m = re.search(r"integrity checks (\d+), failures (\d+)", res.stderr)
    assert m is not None, res.stderr
    checks, failures = map(int, m.groups())
    assert failures == 1 and checks >= 5, res.stderr
    assert re.search(r"integrity: C08 recovered", res.stderr), res.stderr
    assert re.search(r"excluded by fault detection: .*C08", res.stderr), res.stderr
