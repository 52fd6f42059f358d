"""The virtual receiver's RAWX prMes becomes valid by the SOW-decode rule.

Each satellite's first RXM-SFRBX is the first subframe whose preamble came after bit sync;
it is reported at the subframe's end, one subframe period after its first bit reached the
receiver. Under the ``sow`` rule prMes must be valid from the first epoch at or after that
first bit + 0.12 s (D2) / 1.2 s (D1), i.e. long before the SFRBX itself arrives; under the
``subframe`` rule from the SFRBX's arrival. The SFRBX words carry their SOW, checked to be the
subframe the timing says.
"""

from __future__ import annotations

import math

import pytest

from service.core.bds import is_geo
from service.core.bds_nav import parse_header, subframe_start_sow_s
from service.sim.keplerian import table1_ephemerides
from service.sim.scenario import scenario_config
from service.sim.simulator import Simulator, subframe_words

RATE_HZ = 10.0
KNOWN_S = {
    ("sow", "D2"): 0.12,  # 60 bits at 500 bps
    ("sow", "D1"): 1.2,  # 60 bits at 50 bps
    ("subframe", "D2"): 0.6,  # 300 bits
    ("subframe", "D1"): 6.0,
}
PERIOD_S = {"D2": 0.6, "D1": 6.0}


@pytest.mark.parametrize("rule", ["sow", "subframe"])
@pytest.mark.parametrize("seed", [0, 5])
def test_prmes_valid_from_the_rules_instant(rule, seed):
    cfg = scenario_config(seed=seed, duration_s=16.0, rate_hz=RATE_HZ, full_rule=rule)
    ephs = table1_ephemerides(0.0)
    sim = Simulator(ephs, cfg)
    eph_of = {e.prn: e for e in sim.ephemerides}
    first_full: dict[str, float] = {}
    first_sf = {}
    for ep in sim.epochs():
        for sf in ep.subframes:
            first_sf.setdefault(sf.prn, sf)
        for prn, full in zip(ep.prn, ep.full, strict=True):
            if full:
                first_full.setdefault(prn, ep.t_s)
            else:
                assert prn not in first_full, f"{prn} went fractional again at {ep.t_s}"
    assert set(first_sf) == set(first_full) == set(sim.prns)
    for prn, sf in first_sf.items():
        nav = "D2" if is_geo(prn) else "D1"
        assert sf.nav_type == nav
        # the words say which subframe this is: its SOW names the subframe's start
        header = parse_header(subframe_words(eph_of[prn], sf, None), nav)
        assert subframe_start_sow_s(header, nav) == pytest.approx(sf.start_bdt_sow_s)
        preamble_rx_s = sf.received_s - PERIOD_S[nav]
        known_s = preamble_rx_s + KNOWN_S[(rule, nav)]
        expected = math.ceil(round(known_s * RATE_HZ, 6)) / RATE_HZ
        assert first_full[prn] == pytest.approx(expected), (prn, rule, sf)
        if rule == "sow":
            assert first_full[prn] < sf.received_s  # the SOW is known before the SFRBX
