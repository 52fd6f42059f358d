"""Shared pytest set-up.

- One hypothesis profile for every property test: no deadline (a slow machine is not a
  failure), derandomized (the same examples on every run and machine) and no example
  database (nothing carried over from earlier runs).
- ``@pytest.mark.needs("gpsd", ...)``: the test uses these system programs as real peers
  (table in tests/support/peers.py). A missing one skips the test with the Debian package
  to install; with ``BDSFIX_REQUIRE_PEERS=1`` (``.ci/run``) it fails the test instead.
- ``--regen-golden`` rewrites tests/golden/ (gpsd's habit).
"""

from __future__ import annotations

import pytest
from hypothesis import settings

from tests.support.peers import PEERS, REQUIRE_ENV, missing, required

settings.register_profile("bdsfix", deadline=None, derandomize=True, database=None)
settings.load_profile("bdsfix")


def pytest_addoption(parser):
    parser.addoption(
        "--regen-golden",
        action="store_true",
        default=False,
        help="rewrite the golden replay outputs in tests/golden/",
    )


def pytest_collection_modifyitems(config, items):
    for item in items:
        for mark in item.iter_markers("needs"):
            unknown = [p for p in mark.args if p not in PEERS]
            if unknown or not mark.args:
                raise pytest.UsageError(
                    f"{item.nodeid}: needs{mark.args}: name programs listed in "
                    f"tests/support/peers.py (with their Debian package); unknown: {unknown}"
                )


def pytest_runtest_setup(item):
    programs = [p for mark in item.iter_markers("needs") for p in mark.args]
    absent = missing(programs)
    if not absent:
        return
    packages = " ".join(sorted({PEERS[p] for p in absent}))
    why = f"needs {', '.join(absent)} (Debian: apt-get install {packages})"
    if required():
        pytest.fail(f"{why}; {REQUIRE_ENV}=1 makes a missing peer a failure", pytrace=False)
    pytest.skip(why)
