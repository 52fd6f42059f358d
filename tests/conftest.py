"""Shared pytest set-up: ``--regen-golden`` rewrites tests/golden/ (gpsd's habit), and one
hypothesis profile for every property test: no deadline (a slow machine is not a failure),
derandomized (the same examples on every run and machine) and no example database (nothing
carried over from earlier runs)."""

from __future__ import annotations

from hypothesis import settings

settings.register_profile("bdsfix", deadline=None, derandomize=True, database=None)
settings.load_profile("bdsfix")


def pytest_addoption(parser):
    parser.addoption(
        "--regen-golden",
        action="store_true",
        default=False,
        help="rewrite the golden replay outputs in tests/golden/",
    )
