"""The README, walked through as a new user would: every command in its code blocks, in
order, in a fresh virtual environment, with the outputs the README shows.

How the README's code blocks are read:

- ```` ```sh ```` blocks are commands, one per line (``#`` comments dropped). A ```` ```text ````
  block is the output the last command before it printed.
- ```` ```console ```` blocks hold ``$ command`` lines, each followed by what it prints.
- ```` ```sh host ```` blocks set up a host (``sudo``, systemd, certificates in ``/etc``): they
  are not run here (``tests/daemon/test_systemd.py`` checks the unit, and
  ``tests/system/test_service_io.py`` the CURVE keys); every other block is.

Shown output is matched line by line: ``...`` on a line of its own stands for any lines, and a
line ending in `` ...`` for any text after its start. Each run of lines between ``...`` must
appear, in order, in the command's stdout or in its stderr (a reader cannot tell the two
apart on a terminal; here they are captured apart, so they never interleave).

The commands run with ``bash`` in a copy of the working tree with ``../shared`` beside it,
and the fresh environment's ``bin`` first on ``PATH``. ``pip install`` installs from the
package index as a user's would. The suite's own command, ``python -m pytest``, is not run
inside the suite: the walkthrough checks that ``.ci/run`` runs exactly the README's line, and
collects the suite (``--collect-only``) in the fresh environment instead.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field

import pytest

from tests.support.paths import DATA, ROOT

FENCE = re.compile(r"^```([^\n]*)\n(.*?)^```\s*$", re.S | re.M)
TEST_COMMAND = "python -m pytest"


@dataclass
class Step:
    command: str
    shown: list[str] = field(default_factory=list)


def readme_steps(text: str) -> tuple[list[Step], list[str]]:
    """(the commands in order with the output shown for each, the host blocks' first lines)."""
    steps: list[Step] = []
    host: list[str] = []
    for m in FENCE.finditer(text):
        info, body = m.group(1).split(), m.group(2).splitlines()
        lang = info[0] if info else ""
        if lang == "sh" and "host" in info[1:]:
            host.append(body[0] if body else "")
        elif lang == "sh":
            steps += [Step(x.strip()) for x in body if x.strip() and not x.startswith("#")]
        elif lang == "text" and steps:
            steps[-1].shown += body
        elif lang == "console":
            for line in body:
                if line.startswith("$ "):
                    steps.append(Step(line[2:]))
                elif steps:
                    steps[-1].shown.append(line)
    return steps, host


def _matches(line: str, want: str) -> bool:
    return line.startswith(want[:-4]) if want.endswith(" ...") else line == want


def _find(lines: list[str], segment: list[str], start: int) -> int | None:
    for i in range(start, len(lines) - len(segment) + 1):
        if all(_matches(lines[i + k], w) for k, w in enumerate(segment)):
            return i + len(segment)
    return None


def shown_in(shown: list[str], out: str, err: str) -> str | None:
    """None when the shown lines appear as the module docstring says, else what is missing."""
    segments: list[list[str]] = [[]]
    for line in shown:
        if line == "...":
            segments.append([])
        else:
            segments[-1].append(line)
    streams = {"stdout": out.splitlines(), "stderr": err.splitlines()}
    pos = dict.fromkeys(streams, 0)
    for seg in filter(None, segments):
        for name, lines in streams.items():
            end = _find(lines, seg, pos[name])
            if end is not None:
                pos[name] = end
                break
        else:
            return "\n".join(seg)
    return None


def _copy_tree(dest) -> None:
    skip = shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", ".venv", "build", ".*_cache")
    shutil.copytree(ROOT, dest / "bdsfix", ignore=skip)
    (dest / "shared").symlink_to(DATA.parent)


def test_readme_parses_into_the_two_setup_commands_first():
    steps, host = readme_steps((ROOT / "README.md").read_text())
    assert [s.command for s in steps[:2]] == [
        "pip install . && bdsfix replay",
        f"pip install '.[test]' && {TEST_COMMAND}",
    ]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert steps[1].command in ci, ".ci/run must run the README's test command"
    assert all(h.startswith("sudo ") or "create_certificates" in h for h in host), host


@pytest.mark.slow
@pytest.mark.needs("gpsd", "gpspipe")  # the recipe of the daemon with gpsd
def test_readme_walkthrough(tmp_path):
    steps, _ = readme_steps((ROOT / "README.md").read_text())
    _copy_tree(tmp_path)
    work = tmp_path / "bdsfix"
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    script = ["set -u"]
    for i, step in enumerate(steps):
        cmd = step.command.replace(TEST_COMMAND, f"{TEST_COMMAND} --collect-only -q")
        script += [f"{{ {cmd}\n}} >out.{i} 2>err.{i} </dev/null", f"echo $? >rc.{i}"]
    script.append("wait")
    subprocess.run(["bash", "-c", "\n".join(script)], cwd=work, env=env, timeout=1800)
    for i, step in enumerate(steps):
        out, err = (work / f"out.{i}").read_text(), (work / f"err.{i}").read_text()
        rc = int((work / f"rc.{i}").read_text())
        assert rc == 0, f"$ {step.command}\nexit {rc}\n{err[-3000:]}"
        missing = shown_in(step.shown, out, err)
        assert missing is None, (
            f"$ {step.command}\nthe README shows:\n{missing}\n"
            f"--- stdout ---\n{out[-3000:]}\n--- stderr ---\n{err[-3000:]}"
        )
