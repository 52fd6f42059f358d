"""Shared pytest options: ``--regen-golden`` rewrites tests/golden/ (gpsd's habit)."""

from __future__ import annotations


def pytest_addoption(parser):
    parser.addoption(
        "--regen-golden",
        action="store_true",
        default=False,
        help="rewrite the golden replay outputs in tests/golden/",
    )
