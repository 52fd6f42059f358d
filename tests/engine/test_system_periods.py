"""The fast solver's fractional ranges use each satellite's system's code period (issue 18)."""

import math

import numpy as np
import pytest

from service.core.types import MeasurementEpoch
from service.engine.solver import fractionalize

C_M_S = 299_792_458.0


def test_fractionalize_reduces_each_row_modulo_its_own_code_period():
    """Default: the BeiDou GEO C01 stays full; C06 (B1I, 1 ms), G12 (C/A, 1 ms, IS-GPS-200
    3.3.2) and E11 (E1 primary code, 4 ms, Galileo OS SIS ICD 3.4) become fractional modulo
    c times their own period; G01 is not a GEO and is reduced too. An explicit period applies
    to every reduced row, as ``bdsfix solve --period-ms`` asks."""
    prn = ["C01", "C06", "G12", "E11", "G01"]
    pr = np.array([37_123_456.789, 21_000_123.456, 22_000_987.654, 23_456_789.012, 20_111_222.333])
    ep = MeasurementEpoch.from_columns(2161, 345600.0, prn, ["2I"] * 5, pr)
    frac = fractionalize(ep)
    assert math.isfinite(frac.pr_m[0]) and np.isnan(frac.pr_m[1:]).all()
    assert frac.period_s.tolist() == [1e-3, 1e-3, 1e-3, 4e-3, 1e-3]
    for i, t in enumerate(frac.period_s):
        assert frac.frac_pr_m[i] == pytest.approx(math.fmod(pr[i], C_M_S * t), abs=1e-6)
    d1_bit = fractionalize(ep, 20e-3)
    assert d1_bit.period_s.tolist() == [1e-3, 20e-3, 20e-3, 20e-3, 20e-3]
    assert d1_bit.frac_pr_m[3] == pytest.approx(math.fmod(pr[3], C_M_S * 20e-3), abs=1e-6)
