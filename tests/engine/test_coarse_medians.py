"""The coarse-time fix's own median and norm helpers give numpy's values bit for bit.

They replace ``np.median``, ``np.nanmedian`` (over each candidate's used rows) and
``np.linalg.norm`` in the candidate solve and the Doppler position for their per-call cost
alone; the search's outcomes (fixes, integers, declines) depend on those values, so they
must be the same bits, ties, repeated values and NaN rows included.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.engine.coarse import _clock_medians, _median, _row_norms

# residual-like values [m]: clock offsets of km to thousands of km, with exact repeats
VALUES = st.one_of(
    st.floats(-3e8, 3e8, allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, -0.0, 1.5, 299_792.458, -1e-3]),
)


@settings(deadline=None, max_examples=300)
@given(arrays(np.float64, st.tuples(st.integers(1, 30), st.integers(1, 13)), elements=VALUES))
def test_median_is_numpys(a: np.ndarray) -> None:
    assert np.array_equal(_median(a), np.median(a, axis=1))


@settings(deadline=None, max_examples=100)
@given(arrays(np.float64, st.tuples(st.integers(1, 10), st.integers(1, 9)), elements=VALUES))
def test_median_with_nan_rows_is_numpys(a: np.ndarray) -> None:
    a = a.copy()
    a[0, -1] = np.nan
    assert np.array_equal(_median(a), np.median(a, axis=1), equal_nan=True)


@pytest.mark.filterwarnings("ignore:All-NaN slice")  # (np.nanmedian's, a row all NaN)
@settings(deadline=None, max_examples=300)
@given(st.data())
def test_masked_clock_medians_are_nanmedians(data: st.DataObject) -> None:
    k = data.draw(st.integers(1, 25))
    n = data.draw(st.integers(1, 14))
    r = data.draw(arrays(np.float64, (k, n), elements=VALUES))
    clk = data.draw(arrays(np.intp, n, elements=st.integers(0, 2)))
    mask = data.draw(arrays(np.bool_, (k, n)))
    if data.draw(st.booleans()):
        r[data.draw(st.integers(0, k - 1)), data.draw(st.integers(0, n - 1))] = np.nan
    want = np.zeros((k, 3))
    for s in range(3):
        cols = clk == s
        if not cols.any():
            continue
        m = mask[:, cols]
        has = m.any(axis=1)
        want[has, s] = np.nanmedian(np.where(m, r[:, cols], np.nan)[has], axis=1)
    assert np.array_equal(_clock_medians(r, mask, clk, 3), want, equal_nan=True)


@settings(deadline=None, max_examples=200)
@given(arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)), elements=VALUES))
def test_row_norms_are_numpys(d: np.ndarray) -> None:
    assert np.array_equal(_row_norms(d), np.linalg.norm(d, axis=1))
