"""Absurd ranges in a live stream: `bdsfix replay` and `bdsfix run` keep going, publish no
fix outside the plausible shell, never print a traceback, and count what they excluded.

- HKSC RINEX with one range of 1e9 m and one of 1e12 m (two epochs, two satellites);
- the PolyU ZED-F9P UBX capture with one BDS RAWX prMes 300 m off in every 10th RAWX
  (frames re-encoded with a valid checksum, so the receiver "meant" it).
"""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from drivers.ubx import fletcher8
from service.core.geometry import ecef_to_geodetic
from tests.support.paths import DATA, ROOT

HK = DATA / "hksc-2021"
POLYU = DATA / "hk-polyu-f9p-ubx-2024"
ALT_WINDOW_M = (-1_000.0, 1_100_000.0)  # SolverConfig's default plausible shell


def _absurd_rinex(dst: Path) -> list[tuple[str, float]]:
    """HKSC with C09's C2I at the 20th epoch set to 1e9 m and C11's at the 40th to 1e12 m."""
    plan = {20: ("C09", "1000000000.000"), 40: ("C11", "  1.000000E+12")}
    out, done = [], []
    epoch = -1
    with open(HK / "hksc1610.obs", encoding="ascii") as f:
        header = True
        for line in f:
            if header:
                header = "END OF HEADER" not in line
            elif line.startswith(">"):
                epoch += 1
            elif epoch in plan and line.startswith(plan[epoch][0]):
                line = line[:3] + plan[epoch][1] + line[17:]
                done.append((plan[epoch][0], float(plan[epoch][1])))
            out.append(line)
    dst.write_text("".join(out), encoding="ascii")
    return done


def _biased_ubx(dst: Path, bias_m: float = 300.0) -> int:
    """The PolyU capture with the first valid BDS prMes of every 10th RAWX off by bias_m."""
    data = (POLYU / "COM18___9600_240925_072456.ubx").read_bytes()
    frames = Framer(PROTOCOLS).feed(data) + Framer(PROTOCOLS).flush()
    out = bytearray(data)
    n_rawx = n_biased = 0
    for fr in frames:
        raw = fr.raw
        if fr.protocol != "ubx" or raw[2:4] != b"\x02\x15":
            continue
        n_rawx += 1
        if n_rawx % 10:
            continue
        payload = bytearray(raw[6:-2])
        for k in range(payload[11]):  # numMeas
            off = 16 + 32 * k
            gnss, trk = payload[off + 20], payload[off + 30]
            if gnss == 3 and trk & 1:
                (pr,) = struct.unpack_from("<d", payload, off)
                struct.pack_into("<d", payload, off, pr + bias_m)
                n_biased += 1
                break
        body = raw[2:6] + bytes(payload)
        out[fr.offset : fr.offset + len(raw)] = b"\xb5\x62" + body + fletcher8(body)
    dst.write_bytes(bytes(out))
    return n_biased


def _check_run(cmd: list[str], jsonl: Path) -> tuple[str, list[dict]]:
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "RuntimeWarning" not in res.stderr, res.stderr
    for line in res.stderr.splitlines():  # log lines or the replay's own summary, nothing else
        assert line.startswith(("INFO ", "WARNING ", "ERROR ", "bdsfix ", "  ")), line
    recs = [json.loads(x) for x in jsonl.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX" and r["mode"] != "none"]
    assert fixes
    for r in fixes:
        _, _, alt = ecef_to_geodetic(np.asarray(r["x_ecef_m"]))
        assert ALT_WINDOW_M[0] <= float(alt) <= ALT_WINDOW_M[1], r
        assert math.isfinite(r["clock_bias_m"]) and abs(r["clock_bias_m"]) < 1e3 * 3e8
    return res.stderr, recs


def _commands(tmp_path: Path, capture: Path, nav: Path) -> dict[str, tuple[list[str], Path]]:
    py = [sys.executable, "-m", "service"]
    rj, dj = tmp_path / "replay.jsonl", tmp_path / "run.jsonl"
    replay = [*py, "replay", str(capture), "--nav", str(nav), "--max-speed"]
    replay += ["--jsonl-out", str(rj), "--nmea-out", "/dev/null"]
    run = [*py, "run", "--source", str(capture), "--nav", str(nav), "--state-dir"]
    run += [str(tmp_path / "state"), "--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(dj)]
    return {"replay": (replay, rj), "run": (run, dj)}


@pytest.mark.parametrize("command", ["replay", "run"])
def test_absurd_ranges_in_a_rinex_stream(tmp_path, command):
    obs = tmp_path / "absurd.obs"
    assert _absurd_rinex(obs) == [("C09", 1e9), ("C11", 1e12)]
    cmd, jsonl = _commands(tmp_path, obs, HK / "hksc1610.nav")[command]
    stderr, recs = _check_run(cmd, jsonl)
    fixes = [r for r in recs if r["class"] == "FIX"]
    assert len(fixes) == 205 and all(r["mode"] != "none" for r in fixes)
    excluded = [r["excluded"] for r in fixes if "excluded" in r]
    assert [sorted(e) for e in excluded] == [["C09"], ["C11"]]
    assert all("impossible" in next(iter(e.values())) for e in excluded)
    if command == "replay":
        assert "excluded by fault detection: C09 1, C11 1" in stderr, stderr


@pytest.mark.parametrize("command", ["replay", "run"])
def test_a_biased_rawx_prmes_every_10th_epoch(tmp_path, command):
    ubx = tmp_path / "biased.ubx"
    n = _biased_ubx(ubx)
    assert n >= 15
    cmd, jsonl = _commands(tmp_path, ubx, POLYU / "hksc269h.24f")[command]
    stderr, recs = _check_run(cmd, jsonl)
    fixes = [r for r in recs if r["class"] == "FIX"]
    with_excl = [r for r in fixes if r.get("excluded")]
    # every biased epoch that fixes excludes the biased satellite (and no other epoch
    # excludes anything: the capture is otherwise clean)
    assert len(with_excl) >= 0.9 * n, (len(with_excl), n)
    assert len(with_excl) <= n
    if command == "replay":
        assert "excluded by fault detection:" in stderr, stderr
