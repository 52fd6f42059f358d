"""The system programs some tests use as real peers, and the Debian package of each.

A test declares what it needs with ``@pytest.mark.needs("gpsd")`` (tests/conftest.py): it is
skipped, with the package named, when the program is missing, and fails instead when
``BDSFIX_REQUIRE_PEERS=1`` (``.ci/run`` sets it, after installing these packages). Standard
library only: ``.ci/run`` reads this table with the system's python3 before any venv.
"""

from __future__ import annotations

import os
import shutil

PEERS: dict[str, str] = {
    "gpsd": "gpsd",
    "gpspipe": "gpsd-clients",
    "socat": "socat",
    "systemd-analyze": "systemd",
    "rnx2rtkp": "rtklib",
    "chromium": "chromium",
}
"""Program -> Debian package that installs it."""

REQUIRE_ENV = "BDSFIX_REQUIRE_PEERS"


def missing(programs: tuple[str, ...] | list[str]) -> list[str]:
    """The programs of ``programs`` not on PATH."""
    return [p for p in programs if shutil.which(p) is None]


def required() -> bool:
    """Whether a missing peer is a failure (CI) rather than a skip (a fresh machine)."""
    return os.environ.get(REQUIRE_ENV, "") not in ("", "0")


if __name__ == "__main__":  # .ci/run: the packages of the programs that are missing
    print(" ".join(sorted({PEERS[p] for p in missing(list(PEERS))})))
