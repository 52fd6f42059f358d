"""Where the tests find the repository, the real recordings and the golden outputs."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
"""The repository (the working directory of every ``python -m service`` subprocess)."""
DATA = ROOT.parent / "shared" / "data"
"""The real recordings, read in place (``../shared/data`` from the repository)."""
GOLDEN = ROOT / "tests" / "golden"
"""Golden replay outputs (``pytest --regen-golden`` rewrites them)."""
