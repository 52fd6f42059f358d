"""RINEX as IGS publishes it: gzip, Unix compress and Hatanaka compact RINEX are read
transparently, for obs and nav, by ``solve`` and ``replay``: the same output as the plain
files. The compressed copies are made here (gzip from the standard library, Hatanaka and
.Z with the ``hatanaka`` package, independent of the reader)."""

from __future__ import annotations

import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import hatanaka
import pytest

from drivers.rinex import open_text
from drivers.source import is_rinex
from tests.support.paths import DATA, ROOT

OBS = DATA / "hksc-2021" / "hksc1610.obs"
NAV = DATA / "hksc-2021" / "hksc1610.nav"


def _gz(src: Path, dst: Path) -> Path:
    with open(src, "rb") as f, gzip.open(dst, "wb") as g:
        shutil.copyfileobj(f, g)
    return dst


@pytest.fixture(scope="module")
def copies(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    d = tmp_path_factory.mktemp("compressed")
    crx = d / "hksc1610.21d"
    crx.write_bytes(hatanaka.rnx2crx(OBS.read_bytes()))
    dot_z = d / "hksc1610.21d.Z"
    dot_z.write_bytes(hatanaka.compress(crx.read_bytes(), compression="Z"))
    return {
        "gzip": (_gz(OBS, d / "hksc1610.obs.gz"), _gz(NAV, d / "hksc1610.nav.gz")),
        "hatanaka": (crx, NAV),
        "hatanaka.gz": (_gz(crx, d / "hksc1610.crx.gz"), NAV),
        "hatanaka.Z": (dot_z, NAV),
    }


def _solve(obs: Path, nav: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service", "solve", str(obs), str(nav), "--mode", "both"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture(scope="module")
def plain() -> str:
    out = _solve(OBS, NAV)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count('"class":"FIX"') == 2 * 205
    return out.stdout


@pytest.mark.parametrize("form", ["gzip", "hatanaka", "hatanaka.gz", "hatanaka.Z"])
def test_solve_reads_compressed_rinex_like_the_plain_file(copies, plain, form):
    obs, nav = copies[form]
    assert is_rinex(obs)
    with open_text(obs) as fh:
        assert "RINEX VERSION / TYPE" in fh.readline()
    out = _solve(obs, nav)
    assert out.returncode == 0, out.stderr
    assert out.stdout == plain


def test_replay_reads_a_gzip_obs_like_the_plain_file(copies, tmp_path):
    runs = {}
    for name, (obs, nav) in {"plain": (OBS, NAV), "gzip": copies["gzip"]}.items():
        jsonl = tmp_path / f"{name}.jsonl"
        cmd = [sys.executable, "-m", "service", "replay", str(obs), "--nav", str(nav)]
        cmd += ["--max-speed", "--jsonl-out", str(jsonl)]
        out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        runs[name] = jsonl.read_text()
    assert runs["gzip"] == runs["plain"] and runs["plain"].count('"class":"FIX"') == 205


def test_a_damaged_gzip_is_a_one_line_input_error(tmp_path):
    bad = tmp_path / "broken.obs.gz"
    bad.write_bytes(gzip.compress(OBS.read_bytes())[:5000])
    out = _solve(bad, NAV)
    assert out.returncode == 3, (out.returncode, out.stderr)
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
