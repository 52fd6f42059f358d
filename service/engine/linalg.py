"""Small dense linear algebra for the solver's hot path: numpy's own LAPACK gufuncs (the ones
``numpy.linalg.solve``, ``inv`` and ``eigvalsh`` call) and numpy's C einsum, called directly.

An epoch solves about nine 4x4 systems, inverts two matrices and takes two or three
eigenvalue sets; ``numpy.linalg``'s per-call set-up (type checks, an error-state context)
costs more than the LAPACK call itself at that size. The same gufunc gives the same bits.
Where its result is not finite (a singular matrix, no convergence, or non-finite input) the
call is made again through ``numpy.linalg``, so that errors are raised, and results
returned, exactly as numpy's public functions give them. The solver runs under
``np.errstate(all="ignore")``; elsewhere a singular matrix also gives numpy's
"invalid value" warning before the error.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.linalg import _umath_linalg  # numpy's LAPACK gufuncs (numpy/linalg/_linalg.py)


def _c_einsum() -> Callable[..., Any]:
    """numpy's C einsum: what ``numpy.einsum`` calls when not asked to optimize."""
    try:
        from numpy._core.multiarray import c_einsum  # numpy >= 2

        return c_einsum
    except ImportError:  # pragma: no cover (numpy 1.x)
        try:
            from numpy.core.multiarray import c_einsum as c_einsum_1

            return c_einsum_1
        except ImportError:
            return np.einsum


einsum: Callable[..., Any] = _c_einsum()
"""``numpy.einsum(subscripts, *operands)`` (no ``optimize``): the C function it calls, without
its Python wrapper and dispatch, which on the solver's small arrays cost as much as the
sum. The same function gives the same bits."""


def _finite(x: np.ndarray) -> bool:
    """Whether every element of ``x`` is finite, as one reduction: a sum is finite only if
    every term is (it may also overflow, and the caller then takes numpy's path, which
    gives the same result)."""
    return math.isfinite(np.add.reduce(x, axis=None))


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``numpy.linalg.solve(a, b)`` for float64 ``a`` (..., n, n) and ``b`` (n,) or
    (..., n, k)."""
    return solve_finite(a, b)[0]


def solve_finite(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """:func:`solve`, and whether every element of the solution is finite (the check that
    chooses the path, handed on so that the caller need not make it again)."""
    gufunc = _umath_linalg.solve1 if b.ndim == 1 else _umath_linalg.solve
    x = gufunc(a, b, signature="dd->d")
    if _finite(x):
        return x, True
    x = np.linalg.solve(a, b)
    return x, bool(np.isfinite(x).all())


def inv(a: np.ndarray) -> np.ndarray:
    """``numpy.linalg.inv(a)`` for float64 ``a`` (..., n, n)."""
    x = _umath_linalg.inv(a, signature="d->d")
    if _finite(x):
        return x
    return np.linalg.inv(a)


def eigvalsh(a: np.ndarray) -> np.ndarray:
    """``numpy.linalg.eigvalsh(a)`` (lower triangle) for float64 symmetric ``a``."""
    w = _umath_linalg.eigvalsh_lo(a, signature="d->d")
    if _finite(w):
        return w
    return np.linalg.eigvalsh(a)
