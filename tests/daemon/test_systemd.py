"""The shipped unit and example config: hardened, verifiable, and loadable by the daemon."""

import re
import shutil
import subprocess
import sys

import pytest

from service.daemon.config import load_config
from tests.support.paths import ROOT

UNIT = ROOT / "systemd" / "bdsfix.service"
EXAMPLE = UNIT.with_name("bdsfix.toml")


@pytest.mark.needs("systemd-analyze")
def test_exposure_at_most_2():
    out = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", str(UNIT)],
        capture_output=True,
        text=True,
        check=False,
    )
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out.stdout + out.stderr)
    assert m, out.stdout + out.stderr
    assert float(m.group(1)) <= 2.0


@pytest.mark.needs("systemd-analyze")
def test_unit_verifies(tmp_path):
    exe = shutil.which("bdsfix") or sys.executable
    unit = tmp_path / "bdsfix.service"
    unit.write_text(UNIT.read_text().replace("/usr/local/bin/bdsfix", exe))
    out = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, check=False
    )
    bad = [ln for ln in (out.stdout + out.stderr).splitlines() if "bdsfix.service" in ln]
    assert not bad, bad


def test_example_config_loads_and_binds_loopback():
    cfg = load_config(EXAMPLE)
    assert cfg.source.startswith("serial:")
    assert cfg.nmea_tcp.startswith("127.0.0.1:") and "127.0.0.1" in cfg.zmq
