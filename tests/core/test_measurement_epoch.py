"""``MeasurementEpoch``'s two invariants, on a real epoch (hksc1610.obs): each (satellite,
signal) pair is one row, the first of a repeat; a time of week that is not a number is
refused at construction, whichever reader (or mapper) builds the epoch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.core.errors import DecodeError
from service.core.types import MeasurementEpoch
from tests.support.paths import DATA


@pytest.fixture(scope="module")
def epoch() -> MeasurementEpoch:
    reader = RinexObsReader(DATA / "hksc-2021" / "hksc1610.obs", systems="CGE")
    return next(iter(reader))


def _columns(e: MeasurementEpoch, idx: list[int]) -> dict:
    return {
        "prn": [e.prn[i] for i in idx],
        "signal": [e.signal[i] for i in idx],
        "pr_m": e.pr_m[idx],
        "cn0_dbhz": e.cn0_dbhz[idx],
        "doppler_hz": e.doppler_hz[idx],
    }


def test_from_columns_keeps_the_first_row_of_a_repeated_satellite_signal(epoch):
    """The epoch's rows, then its first five again with ranges 1 km longer: the first five
    rows stand, the repeats are gone; the same satellite on another signal is a row of its
    own."""
    n = len(epoch)
    assert n == 34 and len(set(zip(epoch.prn, epoch.signal, strict=True))) == n
    cols = _columns(epoch, [*range(n), *range(5)])
    cols["pr_m"] = np.concatenate([cols["pr_m"][:n], cols["pr_m"][n:] + 1000.0])
    again = MeasurementEpoch.from_columns(epoch.gpst_week, epoch.gpst_tow_s, **cols)
    assert again.prn == epoch.prn and again.signal == epoch.signal
    for name in ("pr_m", "frac_pr_m", "period_s", "cn0_dbhz", "doppler_hz"):
        np.testing.assert_array_equal(getattr(again, name), getattr(epoch, name))
    cols = _columns(epoch, [*range(n), 0])
    cols["signal"][-1] = "7I"  # C01 on B2I beside its B1I row
    other = MeasurementEpoch.from_columns(epoch.gpst_week, epoch.gpst_tow_s, **cols)
    assert len(other) == n + 1 and other.prn[-1] == epoch.prn[0]


@pytest.mark.parametrize("tow_s", [math.nan, math.inf, -math.inf])
def test_an_epoch_without_a_time_is_refused(epoch, tow_s):
    with pytest.raises(DecodeError, match="not a time"):
        MeasurementEpoch.from_columns(epoch.gpst_week, tow_s, **_columns(epoch, [0, 1]))
    with pytest.raises(DecodeError, match="not a time"):
        MeasurementEpoch(
            gpst_week=epoch.gpst_week,
            gpst_tow_s=tow_s,
            prn=epoch.prn,
            signal=epoch.signal,
            pr_m=epoch.pr_m,
            frac_pr_m=epoch.frac_pr_m,
            period_s=epoch.period_s,
            cn0_dbhz=epoch.cn0_dbhz,
            doppler_hz=epoch.doppler_hz,
            lock_s=epoch.lock_s,
        )
