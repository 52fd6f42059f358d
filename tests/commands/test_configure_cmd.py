"""``bdsfix configure`` end to end through a real pty: the virtual receiver (``bdsfix
simulate --pty --wait-config``) set up by the console script, its stream read back with
pyserial and pyubx2, then ``bdsfix run`` (config file with ``configure = true``) on the same
pty until its first fix; a receiver that NAKs one key and one that never answers end with
one line and the README's exit code; ``--dry-run`` decoded back with pyubx2."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from pyubx2 import SET, UBXReader

from service.core.ephemeris import EphemerisStore
from service.sim.scenario import broadcast_table1
from tests.support.paths import ROOT
from tests.support.receiver import (
    ACK_WAIT_S,
    BEIJING_TRUE,
    HANG_S,
    rawx_svs,
    read_stream,
    simulate_wait_config,
    wait_for,
)

BDSFIX = [sys.executable, "-m", "service"]
GEOS = {1, 2, 3, 4, 5}
REFUSED, INPUT = 5, 3  # README "Exit codes", written out
WAIT = ("--timeout-s", str(ACK_WAIT_S))


def _bdsfix(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*BDSFIX, *args], cwd=ROOT, capture_output=True, text=True, timeout=HANG_S
    )


@pytest.mark.parametrize("model", ["f9", "m8"])
def test_configure_then_the_stream_has_rawx_measx_sfrbx_with_geos(tmp_path, model):
    with simulate_wait_config(tmp_path) as sim:
        out = _bdsfix("configure", "--source", sim.device, "--model", model, *WAIT)
        assert out.returncode == 0, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "messages acknowledged" in lines[0], out.stderr
        n = {"f9": 6, "m8": 5}[model]
        assert f"{n} messages acknowledged" in lines[0] and "UART1" in lines[0]
        frames = read_stream(sim.device, 20)
        log = sim.err_path.read_text(errors="replace")
    assert log.count("INFO service.sim.cfg: ACK") == n and "NAK" not in log
    assert {m.identity for _, m in frames} == {"RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"}
    rawx = [m for _, m in frames if m.identity == "RXM-RAWX"]
    assert any(GEOS & {sv for sv, ok in rawx_svs(m).items() if ok} for m in rawx)
    assert any(m.svId in GEOS for _, m in frames if m.identity == "RXM-SFRBX")


def _warm_state(tmp_path: Path) -> Path:
    """The daemon's state directory holding the ephemerides the virtual receiver uses."""
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    store = EphemerisStore()
    store.add_all(broadcast_table1())
    store.save(state / "ephemeris.json")
    return state


def _fixes(path: Path) -> list[dict]:
    if not path.exists():
        return []
    text = path.read_text()
    recs = [json.loads(line) for line in text.splitlines()[: text.count("\n")]]
    return [r for r in recs if r["class"] == "FIX" and r["mode"] != "none"]


def test_run_with_configure_true_sets_the_receiver_up_and_fixes_fast(tmp_path):
    """`bdsfix configure` first, then `bdsfix run` with `configure = true` in its config
    file on the same pty: the set-up restarts the receiver's tracking, and the daemon's
    first fix is a fast fix at the true place, before any conventional one."""
    state = _warm_state(tmp_path)
    jsonl = tmp_path / "fixes.jsonl"
    err = tmp_path / "run.err"
    with simulate_wait_config(tmp_path) as sim:
        assert _bdsfix("configure", "--source", sim.device, *WAIT).returncode == 0
        conf = tmp_path / "bdsfix.toml"
        conf.write_text(
            f'source = "{sim.device}"\nconfigure = true\nconfigure_model = "f9"\n'
            f"configure_rate_hz = 10.0\nconfigure_timeout_s = {ACK_WAIT_S}\n"
            f'state_dir = "{state}"\nnmea_tcp = ""\nzmq = ""\n'
            f'jsonl_out = "{jsonl}"\nlog_level = "info"\n',
            encoding="utf-8",
        )
        with err.open("wb") as err_fh:
            proc = subprocess.Popen(
                [*BDSFIX, "run", "--config", str(conf)], cwd=ROOT, stderr=err_fh
            )
        try:
            wait_for(lambda: any(f["mode"] == "spp" for f in _fixes(jsonl)), "conventional fix")
        finally:
            proc.terminate()
            proc.wait(HANG_S)
    log = err.read_text(errors="replace")
    assert proc.returncode == 0, log[-2000:]
    assert "receiver set-up: " in log and "6 messages acknowledged" in log
    fixes = _fixes(jsonl)
    first = fixes[0]
    assert first["mode"] == "fast" and first["n_frac"] > 0, first
    assert first["since_start_s"] <= 1.5  # data time: the GEOs' D2 SOW, not the D1 one
    lat, lon, alt = BEIJING_TRUE
    dn = (first["lat_deg"] - lat) * 111_000.0
    de = (first["lon_deg"] - lon) * 111_000.0 * math.cos(math.radians(lat))
    assert math.hypot(dn, de) < 15.0 and abs(first["alt_m"] - alt) < 30.0, first
    # the restart the set-up caused is in the simulator's log as the signals' ACK
    assert sim.err_path.read_text().count("CFG_SIGNAL_BDS_ENA=1") == 2


def test_a_receiver_that_refuses_a_key(tmp_path):
    with simulate_wait_config(tmp_path, "--nak", "CFG_BDS_USE_GEO_PRN") as sim:
        out = _bdsfix("configure", "--source", sim.device, *WAIT)
        frames = read_stream(sim.device, 20)
        state = _warm_state(tmp_path)
        run = _bdsfix(
            "run", "--source", sim.device, "--configure", "true", "--state-dir", str(state),
            "--configure-timeout-s", str(ACK_WAIT_S),
            "--nmea-tcp", "", "--zmq", "", "--log-level", "warning",
        )  # fmt: skip
    assert out.returncode == REFUSED, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(f"bdsfix configure: error: {sim.device} (f9, port uart1): ")
    assert "refused (ACK-NAK) CFG-VALSET CFG_BDS_USE_GEO_PRN=1 (RAM)" in lines[0]
    assert "the other 5 messages were acknowledged and are in effect" in lines[0]
    # what was acknowledged is in effect: measurements flow, without the GEOs
    svs = set().union(*(rawx_svs(m) for _, m in frames if m.identity == "RXM-RAWX"))
    assert svs and not svs & GEOS
    # the daemon refuses to start half set up, with the same line and code
    assert run.returncode == REFUSED, run.stderr
    errors = [ln for ln in run.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1 and "CFG_BDS_USE_GEO_PRN" in errors[0], run.stderr
    assert "bdsfix running" not in run.stderr


def test_a_receiver_that_never_answers(tmp_path):
    with simulate_wait_config(tmp_path, "--no-answer") as sim:
        out = _bdsfix("configure", "--source", sim.device, "--timeout-s", "0.3")
    assert out.returncode == INPUT, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert (
        "no answer (ACK/NAK) to CFG-VALSET CFG_SIGNAL_BDS_ENA=1, CFG_SIGNAL_BDS_B1_ENA=1"
        in (lines[0])
    )
    assert "within 0.3 s, sent twice" in lines[0] and "nothing was acknowledged" in lines[0]


def _dry_run(*args: str) -> list:
    out = _bdsfix("configure", "--dry-run", *args)
    assert out.returncode == 0, out.stderr
    assert "nothing sent" in out.stderr
    msgs = []
    for line in out.stdout.splitlines():
        hexpart, _, what = line.partition("  # ")
        assert what, line
        msgs.append(UBXReader.parse(bytes.fromhex(hexpart), msgmode=SET))
    return msgs


def test_dry_run_prints_the_messages_in_hex():
    msgs = _dry_run("--source", "/dev/ttyACM0", "--rate-hz", "5", "--save")
    keys = [{k: v for k, v in vars(m).items() if k.startswith("CFG_")} for m in msgs]
    assert [m.identity for m in msgs] == ["CFG-VALSET"] * 7
    assert keys[:6] == [
        {"CFG_SIGNAL_BDS_ENA": 1, "CFG_SIGNAL_BDS_B1_ENA": 1},
        {"CFG_BDS_USE_GEO_PRN": 1},
        {"CFG_RATE_MEAS": 200, "CFG_RATE_NAV": 1},
        {"CFG_MSGOUT_UBX_RXM_RAWX_USB": 1},
        {"CFG_MSGOUT_UBX_RXM_MEASX_USB": 1},
        {"CFG_MSGOUT_UBX_RXM_SFRBX_USB": 1},
    ]
    assert (msgs[-1].ram, msgs[-1].bbr, msgs[-1].flash) == (0, 1, 1)  # --save, last
    assert len(keys[-1]) == 8
    m8 = _dry_run("--model", "m8")
    assert [m.identity for m in m8] == ["CFG-GNSS", "CFG-RATE", "CFG-MSG", "CFG-MSG", "CFG-MSG"]
    assert [m.rateUART1 for m in m8[2:]] == [1, 1, 1]
