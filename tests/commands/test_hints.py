"""The summaries' hints name only flags the command has (issue 23: ``run --source tcp:...``
refused, and its hint said ``--gps-week``, which ``run`` does not accept)."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys

import pytest

from service.commands.cli import build_parser
from service.commands.summary import no_epochs_hint
from service.core.declines import Decline, hint
from tests.support.paths import ROOT

HANG_S = 120.0


def _options(command: str) -> set[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # the subparsers action
    return set(sub.choices[command]._option_string_actions)  # type: ignore[attr-defined]


@pytest.mark.parametrize("command", ["run", "replay", "solve"])
def test_every_hint_names_only_the_commands_own_flags(command):
    options = _options(command)
    texts = [no_epochs_hint(command), no_epochs_hint(command, {"source_open_failures": 3})]
    texts += [hint(code, command) or "" for code in Decline]
    for text in texts:
        # a flag of another command is named with that command ('bdsfix replay ... --x')
        own = re.sub(r"'bdsfix \w+[^']*'", "", text)
        for flag in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", own):
            assert flag in options, f"{command}: {text}"


def test_run_on_a_refused_tcp_source_says_it_never_opened(tmp_path):
    """A TCP port bound but not listening refuses every connection (no race with another
    program); ``run`` retries until SIGTERM, then its summary says the source never opened
    and names no flag it lacks."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        port = held.getsockname()[1]
        argv = [sys.executable, "-m", "service", "run", "--source", f"tcp:127.0.0.1:{port}"]
        argv += ["--state-dir", str(tmp_path / "state"), "--nmea-tcp", "", "--zmq", ""]
        proc = subprocess.Popen(argv, cwd=ROOT, stderr=subprocess.PIPE, text=True)
        try:
            for line in proc.stderr:  # until the first refusal is logged
                if "cannot open" in line:
                    break
            proc.send_signal(signal.SIGTERM)
            rest = proc.communicate(timeout=HANG_S)[1]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 0, rest
    assert "bdsfix run: 0 epochs" in rest
    assert "the source never opened" in rest and "attempts" in rest
    assert "--gps-week" not in rest
