"""``bdsfix configure`` and ``bdsfix run`` with ``configure = true`` keep their ``--timeout-s``
whatever the device sends (issue 23): a device on a real pty streaming NMEA at the pace of
115200 baud, random bytes, or a UBX header claiming 65,535 bytes followed by a trickle, and
never answering. Each run ends with exit 3 and one line naming the timeout. The subprocess
timeout (``HANG_S``) only stops a hung run; nothing is judged by the time it took."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support.paths import ROOT
from tests.support.talker import HANG_S, KINDS, talking_device

BDSFIX = [sys.executable, "-m", "service"]
INPUT = 3  # README "Exit codes": no answer from the receiver
NO_ANSWER = (
    "no answer (ACK/NAK) to CFG-VALSET CFG_SIGNAL_BDS_ENA=1, CFG_SIGNAL_BDS_B1_ENA=1 (RAM) "
    "within 0.3 s, sent twice ("
)


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*BDSFIX, *args], cwd=ROOT, capture_output=True, text=True, timeout=HANG_S
    )


@pytest.mark.parametrize("kind", KINDS)
def test_configure_gives_up_at_its_timeout_whatever_the_device_sends(kind):
    with talking_device(kind) as device:
        out = _run("configure", "--source", device, "--timeout-s", "0.3")
    assert out.returncode == INPUT, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(f"bdsfix configure: error: {device} (f9, port uart1): ")
    assert NO_ANSWER in lines[0], lines[0]  # then how many bytes were heard
    assert "nothing was acknowledged" in lines[0]


@pytest.mark.parametrize("kind", KINDS)
def test_run_with_configure_gives_up_at_its_timeout_whatever_the_device_sends(tmp_path, kind):
    with talking_device(kind) as device:
        out = _run(
            "run", "--source", device, "--configure", "true", "--configure-timeout-s", "0.3",
            "--state-dir", str(tmp_path / "state"), "--nmea-tcp", "", "--zmq", "",
            "--log-level", "warning",
        )  # fmt: skip
    assert out.returncode == INPUT, out.stderr
    errors = [ln for ln in out.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1 and NO_ANSWER in errors[0], out.stderr
    assert "bdsfix running" not in out.stderr
