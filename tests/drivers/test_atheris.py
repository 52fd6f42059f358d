"""Bounded atheris (libFuzzer) runs of every driver harness in ``tests/drivers/fuzz_atheris.py``.

Each target runs in its own process on a corpus seeded from the real captures, bounded by
``-runs`` and ``-max_total_time``, with libFuzzer's ``-timeout`` as the per-input hang
detector. An exception the harness does not allow, or a hang, makes libFuzzer exit
non-zero and write the input as ``crash-*``/``timeout-*``; the test prints it. The number
of executions is reported, not asserted beyond being positive (no performance claims).
"""

from __future__ import annotations

import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

HARNESS = Path(__file__).with_name("fuzz_atheris.py")
TARGETS = ("framer", "decoder", "ubx", "rtcm", "sfrbx", "rinex_obs", "rinex_nav", "gnsslogger")
MAX_TIME_S = 3
MAX_RUNS = 200_000
HANG_S = 60  # one input running this long is a hang (a loaded machine is not)


def _fuzz(target: str, workdir: Path) -> tuple[int, str, int]:
    corpus = workdir / target / "corpus"
    corpus.mkdir(parents=True)
    cmd = [
        sys.executable,
        str(HARNESS),
        target,
        f"-runs={MAX_RUNS}",
        f"-max_total_time={MAX_TIME_S}",
        f"-timeout={HANG_S}",
        "-max_len=4096",
        "-seed=1",
        "-print_final_stats=1",
        f"-artifact_prefix={workdir / target}/",
        str(corpus),
    ]
    proc = subprocess.run(
        cmd,
        cwd=workdir / target,
        capture_output=True,
        text=True,
        timeout=MAX_TIME_S + 2 * HANG_S + 60,  # libFuzzer reports a hang before this
        env={"BDSFIX_FUZZ_TMP": str(workdir / target), "PATH": "/usr/bin:/bin"},
    )
    out = proc.stdout + proc.stderr
    runs = re.search(r"^Done (\d+) runs", out, re.M)
    return proc.returncode, out, int(runs.group(1)) if runs else -1


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, tuple[int, str, int]]:
    workdir = tmp_path_factory.mktemp("atheris")
    with ThreadPoolExecutor(max_workers=2) as pool:  # two cores
        return dict(zip(TARGETS, pool.map(lambda t: _fuzz(t, workdir), TARGETS), strict=True))


@pytest.mark.slow
@pytest.mark.parametrize("target", TARGETS)
def test_atheris_finds_no_crash_or_hang(results, target):
    rc, stderr, runs = results[target]
    seeded = re.search(r"seeded (\d+) inputs", stderr)
    print(f"atheris {target}: {runs} executions, {seeded.group(1) if seeded else '?'} seeds")
    tail = "\n".join(line for line in stderr.splitlines() if "Instrumenting" not in line)
    assert rc == 0, tail[-3000:]
    assert runs > 0 and seeded is not None and int(seeded.group(1)) > 0
