"""The shipped unit and example config: hardened, verifiable, and loadable by the daemon;
the README's install steps, run in a temporary root."""

import os
import re
import shutil
import subprocess
import sys

import pytest

from service.daemon.config import load_config
from tests.support.paths import ROOT

UNIT = ROOT / "systemd" / "bdsfix.service"
EXAMPLE = UNIT.with_name("bdsfix.toml")
INSTALLED_EXE = "/opt/bdsfix/bin/bdsfix"
"""Where the README's install steps put the program, and the unit's ExecStart finds it."""


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
    assert f"ExecStart={INSTALLED_EXE} " in UNIT.read_text()
    unit.write_text(UNIT.read_text().replace(INSTALLED_EXE, exe))
    out = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, check=False
    )
    bad = [ln for ln in (out.stdout + out.stderr).splitlines() if "bdsfix.service" in ln]
    assert not bad, bad


def test_example_config_loads_and_binds_loopback():
    cfg = load_config(EXAMPLE)
    assert cfg.source.startswith("serial:")
    assert cfg.nmea_tcp.startswith("127.0.0.1:") and "127.0.0.1" in cfg.zmq


def _install_steps() -> list[str]:
    """The commands of the README's systemd install block (its ``sh host`` block under
    "Install as a service"), comments dropped."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Install as a service (systemd)", 1)[1]
    block = re.search(r"^```sh host\n(.*?)^```", section, re.S | re.M)
    assert block, "no sh host block under 'Install as a service'"
    lines = [re.sub(r"\s+#.*$", "", x).strip() for x in block.group(1).splitlines()]
    return [x for x in lines if x and not x.startswith("#")]


@pytest.mark.slow
@pytest.mark.needs("systemd-analyze")
def test_readme_install_steps_in_a_temporary_root(tmp_path):
    """Debian 12 refuses ``sudo pip install .`` (PEP 668), and the unit named
    /usr/local/bin (issue 23). The README's steps, without ``sudo``, with ``/opt`` and
    ``/etc`` moved under a temporary root and the host's package and service managers left
    out (apt-get, systemctl, journalctl), from a copy of the tree: pip may install only
    into a virtual environment (``PIP_REQUIRE_VIRTUALENV``, no venv on PATH), as on Debian
    12. The unit they install starts the program they installed (``systemd-analyze
    verify`` with its paths moved the same way), which reads the config they installed."""
    root = tmp_path / "root"
    (root / "etc/systemd/system").mkdir(parents=True)  # there on any systemd host
    tree = tmp_path / "bdsfix"
    skip = shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", "build", ".*_cache")
    shutil.copytree(ROOT, tree, ignore=skip)
    moved = lambda text: re.sub(r"(?<![\w.])/(opt|etc)/", f"{root}/\\1/", text)  # noqa: E731
    host_only = ("apt-get ", "systemctl ", "journalctl ")
    steps = [
        moved(x.replace("sudo ", ""))
        for x in _install_steps()
        if not x.removeprefix("sudo ").startswith(host_only)
    ]
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env |= {"PATH": "/usr/bin:/bin", "PIP_REQUIRE_VIRTUALENV": "1"}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    for step in steps:
        run = subprocess.run(
            ["bash", "-c", step], cwd=tree, env=env, capture_output=True, text=True, timeout=1800
        )
        assert run.returncode == 0, f"$ {step}\n{run.stderr[-3000:]}"

    installed = root / "etc/systemd/system/bdsfix.service"
    unit = installed.read_text()
    exec_start = re.search(r"^ExecStart=(\S+) run --config (\S+)$", unit, re.M)
    assert exec_start, unit
    exe, config = (moved(x) for x in exec_start.groups())
    assert exe == moved(INSTALLED_EXE) and os.access(exe, os.X_OK), exe
    check = subprocess.run(
        [
            os.path.join(os.path.dirname(exe), "python"),
            "-c",
            "import sys; from service.daemon.config import load_config; "
            "print(load_config(sys.argv[1]).source)",
            config,
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert check.returncode == 0 and check.stdout.startswith("serial:"), check.stderr
    assert subprocess.run([exe, "run", "--help"], capture_output=True, check=False).returncode == 0
    verified = tmp_path / "bdsfix.service"
    verified.write_text(unit.replace(INSTALLED_EXE, exe))
    out = subprocess.run(
        ["systemd-analyze", "verify", str(verified)], capture_output=True, text=True, check=False
    )
    bad = [ln for ln in (out.stdout + out.stderr).splitlines() if "bdsfix.service" in ln]
    assert not bad, bad
