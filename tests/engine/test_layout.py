"""The unknowns as data (service.engine.layout): a clock per satellite system.

Rows named for another system ("G06", ...) get a receiver clock of their own: the solver
recovers an inter-system bias put on them, the redundancy is rows - (3 + clocks), and the
statistics use it. The other system's rows are physically real: HKSC's own BeiDou MEO/IGSO
measurements and broadcast orbits, relabelled, with a known bias added to their ranges.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.ephemeris import EphemerisStore
from service.core.systems import GnssSystem
from service.core.types import MeasurementEpoch
from service.engine.layout import BDS_ONLY, Layout, layout_of
from service.engine.solver import SolverConfig, solve, solve_many
from service.output.records import fix_record
from tests.support.independent import HKSC_TRUTH_ECEF_M
from tests.support.paths import DATA
from tests.support.relabel import ISB_M, Relabelled, relabel
from tests.support.schema import validate


@pytest.fixture(scope="module")
def hksc() -> tuple[list[MeasurementEpoch], EphemerisStore, object]:
    store, iono = load_navigation([str(DATA / "hksc-2021" / "hksc1610.nav")])
    return list(RinexObsReader(DATA / "hksc-2021" / "hksc1610.obs"))[::20], store, iono


def test_layout_counts_one_clock_per_system():
    assert layout_of(("C01", "C06")) is BDS_ONLY
    assert BDS_ONLY.n_params == 4 and BDS_ONLY.redundancy(10) == 6
    two = layout_of(("G12", "C01", "E03", "C06"))
    assert two.systems == (GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL)
    assert two.n_params == 6 and two.redundancy(10) == 4
    assert two.names == ("x", "y", "z", "clock_C", "clock_G", "clock_E")
    assert list(two.clock_index(("G12", "C01", "E03", "C06"))) == [1, 0, 2, 0]
    vel = Layout((GnssSystem.BDS,), problem="velocity", coarse_time=False)
    assert vel.names == ("vx", "vy", "vz", "drift_C") and vel.n_params == 4
    g = two.design(np.eye(3)[[0, 1, 2, 0]], two.clock_index(("G12", "C01", "E03", "C06")))
    assert g.shape == (4, 6)
    assert g[:, 3:].tolist() == [[0, 1, 0], [1, 0, 0], [0, 0, 1], [1, 0, 0]]


@pytest.mark.parametrize("take", [3, 5])
def test_rows_of_another_system_get_their_own_clock(hksc, take):
    epochs, store, iono = hksc
    cfg = SolverConfig()
    for ep in epochs:
        ref = solve(ep, store, iono, cfg, "spp")
        mixed = relabel(ep, take)
        fix = solve(mixed, Relabelled(store), iono, cfg, "spp")  # type: ignore[arg-type]
        assert fix.mode == "spp", fix.reason
        n_g = sum(p.startswith("G") for p in fix.used)
        assert n_g == take
        assert fix.redundancy == len(fix.used) - 5  # x, y, z and two clocks
        assert set(fix.clocks_m) == {"C", "G"}
        assert fix.clock_bias_m == fix.clocks_m["C"]
        # the bias is recovered, and the position is as good as BeiDou alone gives
        isb = fix.clocks_m["G"] - fix.clocks_m["C"]
        assert isb == pytest.approx(ISB_M, abs=3.0)
        err = np.linalg.norm(np.subtract(fix.x_ecef_m, HKSC_TRUTH_ECEF_M))
        ref_err = np.linalg.norm(np.subtract(ref.x_ecef_m, HKSC_TRUTH_ECEF_M))
        assert err <= max(2.0 * ref_err, 5.0)
        assert fix.chi2 is not None and fix.chi2 <= fix.chi2_max


def test_fix_records_carry_each_systems_clock(hksc):
    """A FIX record of rows from two systems carries both clocks (``clocks_m``, 0.1 mm);
    a BeiDou-only fix's record has ``clock_bias_m`` alone (docs/architecture.md, JSONL)."""
    epochs, store, iono = hksc
    ep = epochs[0]
    bds = fix_record(solve(ep, store, iono, SolverConfig(), "spp"))
    assert "clocks_m" not in bds and validate(bds) == []
    fix = solve(relabel(ep, 4), Relabelled(store), iono, SolverConfig(), "spp")  # type: ignore[arg-type]
    rec = fix_record(fix)
    assert validate(rec) == []
    assert list(rec["clocks_m"]) == ["C", "G"]
    assert rec["clocks_m"]["C"] == rec["clock_bias_m"]
    assert rec["clocks_m"]["G"] - rec["clocks_m"]["C"] == pytest.approx(ISB_M, abs=3.0)
    for system, clock_m in fix.clocks_m.items():
        assert rec["clocks_m"][system] == pytest.approx(clock_m, abs=5e-5)


def test_one_clock_for_every_system_would_fail_the_test(hksc):
    """Without its own clock the bias is a fault: the same rows named C fail the chi-square
    test (or exclusion removes them), which is why the layout gives each system a clock."""
    epochs, store, iono = hksc
    ep = epochs[0]
    biased = relabel(ep, 3)
    as_bds = replace(biased, prn=ep.prn)  # the same ranges, all named for BeiDou
    fix = solve(as_bds, store, iono, SolverConfig(), "spp")
    assert not fix.ok or fix.excluded
    mixed = solve(biased, Relabelled(store), iono, SolverConfig(), "spp")  # type: ignore[arg-type]
    assert mixed.ok and not mixed.excluded


@pytest.mark.parametrize("take", [0, 4])
def test_a_chunk_solves_the_mixed_epochs_with_a_clock_per_system(hksc, take):
    """The kernel gives rows of another system their own clock column (the layout of its
    rows); a chunk that mixes epochs of one and of two systems solves each layout's epochs
    together, and each gets what it gets alone (the same decisions, clocks and positions
    within 1e-6 m)."""
    epochs, store, iono = hksc
    mixed = [relabel(ep, take) if k % 2 else ep for k, ep in enumerate(epochs)]
    one = [solve(ep, Relabelled(store), iono, solver="spp") for ep in mixed]  # type: ignore[arg-type]
    many = solve_many(mixed, Relabelled(store), iono, solver="spp")  # type: ignore[arg-type]
    for a, b in zip(one, many, strict=True):
        assert (a.mode, a.used, a.redundancy) == (b.mode, b.used, b.redundancy)
        assert set(a.clocks_m) == set(b.clocks_m)
        for s, c in a.clocks_m.items():
            assert abs(b.clocks_m[s] - c) <= 1e-6
        assert np.linalg.norm(np.subtract(a.x_ecef_m, b.x_ecef_m)) <= 1e-6
    assert sum(len(f.clocks_m) == 2 for f in many) == (len(epochs) // 2 if take else 0)


def test_the_coarse_time_column_is_each_rows_range_rate(hksc):
    """``Layout(coarse_time=True)``: the fifth column is d rho / d t of each row (van
    Diggelen's coarse-time row), checked against the ranges of HKSC's broadcast orbits
    10 ms apart; the time prior is a row of the redundancy."""
    from service.core.orbit import sat_pos_clock
    from service.core.timebase import gpst_to_bdt

    epochs, store, _ = hksc
    ep = epochs[0]
    week, sow = gpst_to_bdt(ep.gpst_week, ep.gpst_tow_s)
    ephs = [e for p in ep.prn if (e := store.select(p, week, sow)) is not None]
    arr = store.arrays(ephs)
    t = np.full(len(ephs), sow - 0.075)
    p0, _ = sat_pos_clock(arr, week, t)
    p1, _ = sat_pos_clock(arr, week, t + 0.01)
    x = np.asarray(HKSC_TRUTH_ECEF_M)
    los = (p0 - x) / np.linalg.norm(p0 - x, axis=1)[:, None]
    rate = np.einsum("ij,ij->i", los, (p1 - p0) / 0.01)
    lay = Layout(coarse_time=True)
    g = lay.design(los, None, rate)
    assert lay.names[-1] == "coarse_time" and lay.time_column == 4 and g.shape == (len(ephs), 5)
    drho = (np.linalg.norm(p1 - x, axis=1) - np.linalg.norm(p0 - x, axis=1)) / 0.01
    assert np.abs(g[:, 4]).max() > 100.0  # (MEOs: hundreds of m/s)
    np.testing.assert_allclose(g[:, 4], drho, atol=0.05)
    np.testing.assert_array_equal(g[:, :4], BDS_ONLY.design(los))
    with pytest.raises(ValueError):
        lay.design(los)
    with pytest.raises(ValueError):
        _ = BDS_ONLY.time_column
    # six ranges and the time prior's row against five unknowns: redundancy 2; two
    # systems' layout with one system's rows only: that system's clock alone is solved
    assert lay.redundancy(6 + 1) == 2
    two = Layout((GnssSystem.BDS, GnssSystem.GPS), coarse_time=True)
    assert two.redundancy(7, clocks_used=1) == 2 and two.redundancy(7) == 1
