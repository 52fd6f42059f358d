"""The service with real peers: a ZeroMQ SUB socket, gpsd as an NMEA client, and the daemon
reading UBX from a pseudo-terminal through pyserial."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.support.gpsd import gpsd_watching
from tests.support.paths import DATA, ROOT
from tests.support.replay import HANG_S, LiveReplay

HK = DATA / "hksc-2021"
POLYU = DATA / "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx"
POLYU_NAV = DATA / "hk-polyu-f9p-ubx-2024/hksc269h.24f"
BDSFIX = [sys.executable, "-m", "service"]

# The contract of docs/architecture.md, written out here (not taken from the code under test).
SCHEMA = {
    "FIX": {
        "required": {
            "class": str,
            "solver": str,
            "mode": str,
            "gpst_week": int,
            "gpst_tow_s": float,
            "n_full": int,
            "n_frac": int,
        },
        "optional": {
            "x_ecef_m": list,
            "lat_deg": float,
            "lon_deg": float,
            "alt_m": float,
            "clock_bias_m": float,
            # a fix of rows from several systems (issue 19): each system's clock and count
            "clocks_m": dict,
            "used_by_system": dict,
            "gdop_full": float,
            "pdop": float,
            "ambiguity": dict,
            "resid_rms_m": float,
            "reason": str,
            "reason_code": str,
            "since_start_s": float,
            # integrity (issue 9): the test, its state and the protection levels
            "redundancy": int,
            "chi2": float,
            "chi2_max": float,
            "raim": str,
            "hpl_m": float,
            "vpl_m": float,
            "std_enu_m": list,
            "excluded": dict,
            # the coarse-time first fix (issue 20)
            "method": str,
            "time_offset_s": float,
            # velocity from Doppler (issue 18)
            "v_enu_m_s": list,
            "std_v_enu_m_s": list,
            "speed_m_s": float,
            "std_speed_m_s": float,
            "course_deg": float,
            "std_course_deg": float,
            "clock_drift_m_s": float,
            "std_clock_drift_m_s": float,
        },
    },
    "TRACK": {
        "required": {
            "class": str,
            "prn": str,
            "event": str,
            "nav_type": str,
            "gpst_week": int,
            "gpst_tow_s": float,
            "since_start_s": float,
        },
        "optional": {"sow_s": float, "full_since_s": float},
    },
    "STATUS": {"required": {"class": str, "counters": dict}, "optional": {}},
    "SKY": {
        "required": {"class": str, "gpst_week": int, "gpst_tow_s": float, "satellites": list},
        "optional": {},
    },
}


def _valid(topic: str, rec: dict) -> None:
    sch = SCHEMA[topic]
    assert rec["class"] == topic
    for k, t in sch["required"].items():
        assert k in rec and isinstance(rec[k], (int, float) if t is float else t), (topic, k)
    for k, v in rec.items():
        assert k in sch["required"] or k in sch["optional"], (topic, k)
        assert v is not None
    if topic == "FIX":
        assert rec["solver"] in ("fast", "spp") and rec["mode"] in ("fast", "spp", "none")
        assert ("reason" in rec) == (rec["mode"] == "none")
        if rec["mode"] != "none":  # a published fix says how far it can be trusted
            assert rec["raim"] in ("pass", "unprotected", "untested")
            assert (rec["raim"] == "pass") == ("hpl_m" in rec and "vpl_m" in rec)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


RESTART_S = 150.0  # data time of the restart in the HKSC replay below


def test_zmq_subscriber_gets_valid_fix_track_status(tmp_path):
    """A SUB socket on a paced HKSC replay with a restart (fast fixes, TRACK events): every
    record is valid, and from its first message on the subscriber gets exactly what the
    replay published: the FIX and TRACK records of its JSONL, SKY, and the final STATUS
    (which counts every FIX published)."""
    jsonl = tmp_path / "fixes.jsonl"
    args = ["replay", str(HK / "hksc1610.obs"), "--nav", str(HK / "hksc1610.nav")]
    args += ["--restart-at", str(RESTART_S), "--speed", "40", "--jsonl-out", str(jsonl)]
    with LiveReplay(args, topics=(b"",)) as replay:
        run = replay.finish()
    assert run.rc == 0, run.stderr[-2000:]
    for topic, rec in run.records:
        _valid(topic, rec)
    written = [json.loads(line) for line in jsonl.read_text().splitlines()]
    got = [rec for topic, rec in run.records if topic in ("FIX", "TRACK")]
    assert got, "no FIX or TRACK received"
    # the subscriber was in before the restart (the replay is paced: 5 s for 205 epochs)
    t0 = written[0]["gpst_tow_s"]
    assert got[0]["gpst_tow_s"] < t0 + RESTART_S, f"joined late: {got[0]}"
    assert got == written[len(written) - len(got) :]  # nothing lost or changed since
    assert sum(rec["class"] == "TRACK" for rec in got) >= 16
    assert sum(rec["class"] == "FIX" and rec["mode"] == "fast" for rec in got) >= 1
    assert any(topic == "SKY" for topic, _ in run.records)
    fixes_written = sum(rec["class"] == "FIX" for rec in written)
    assert run.final["counters"]["zmq_FIX"] == fixes_written == 205


@pytest.mark.needs("gpsd")
def test_gpsd_reports_our_fixes_as_tpv_mode_3(tmp_path):
    """`bdsfix replay` of the PolyU UBX capture (196 epochs) with NMEA on TCP and gpsd as its
    client: gpsd's mode-3 TPV reports are our JSONL fixes within 1 m. The capture goes
    through stdin and is written only once the replay's STATUS counts gpsd as a client, so
    no epoch is lost to anybody's start-up; 40 timed reports are collected."""
    jsonl = tmp_path / "fixes.jsonl"
    tpv: list[dict] = []
    for _attempt in range(3):  # the free port may be taken before the replay binds it
        nmea_port = _free_port()
        args = ["replay", "-", "--nav", str(POLYU_NAV), "--speed", "50"]
        args += ["--nmea-tcp", f"127.0.0.1:{nmea_port}", "--jsonl-out", str(jsonl)]
        with LiveReplay(args, stdin=True) as replay:
            try:
                replay.wait_status(lambda rec: True, "the replay's first STATUS")
            except AssertionError:
                if "in use" in replay.stderr():
                    continue
                raise
            with gpsd_watching(f"tcp://127.0.0.1:{nmea_port}", "-G") as gpsd:
                replay.wait_status(
                    lambda rec: rec["counters"].get("nmea_clients", 0) >= 1, "gpsd as a client"
                )
                replay.feed(POLYU.read_bytes())
                deadline = time.monotonic() + HANG_S
                while len(tpv) < 40:
                    assert time.monotonic() < deadline, f"hung: {len(tpv)} TPV, {gpsd.output()}"
                    ended = replay.proc.poll() is not None
                    got = gpsd.messages(1.0)
                    # gpsd can report a mode-3 TPV before its cycle has a date (GGA
                    # carries only time of day); only timed reports are matched.
                    tpv += [m for m in got if m.get("class") == "TPV" and m.get("mode") == 3]
                    tpv = [m for m in tpv if "time" in m]
                    if ended and not got:  # the stream is over and gpsd has said it all
                        break
            run = replay.finish()
        assert run.rc == 0, run.stderr[-2000:]
        break
    assert len(tpv) >= 20, len(tpv)
    ours = {}
    for line in jsonl.read_text().splitlines():
        r = json.loads(line)
        if r["class"] == "FIX" and r["mode"] != "none":
            ours[round(r["gpst_tow_s"] - r["clock_bias_m"] / 299792458.0 - 18) % 86400] = r
    matched = 0
    for t in tpv:
        hh, mm, ss = t["time"][11:19].split(":")
        key = (int(hh) * 3600 + int(mm) * 60 + int(ss)) % 86400
        r = ours.get(key)
        if r is None:
            continue
        dn = (t["lat"] - r["lat_deg"]) * 111_000
        de = (t["lon"] - r["lon_deg"]) * 111_000 * np.cos(np.radians(r["lat_deg"]))
        dh = t.get("altHAE", t.get("alt", r["alt_m"])) - r["alt_m"]
        assert np.sqrt(dn * dn + de * de + dh * dh) < 1.0, (t, r)
        matched += 1
    assert matched >= 20


@pytest.mark.needs("gpsd")
def test_gpsd_reports_the_static_scenarios_speed_as_near_zero():
    """`bdsfix replay` of the built-in (static) scenario at 4x real time with NMEA on TCP and
    gpsd as its client: every mode-3 TPV that gpsd reports carries a speed (from our RMC and
    VTG) of at most 0.2 m/s; at least 20 of them are collected."""
    tpv: list[dict] = []
    for _attempt in range(3):  # the free port may be taken before the replay binds it
        nmea_port = _free_port()
        args = ["replay", "--speed", "4", "--nmea-tcp", f"127.0.0.1:{nmea_port}"]
        with LiveReplay(args) as replay:
            try:
                replay.wait_status(lambda rec: True, "the replay's first STATUS")
            except AssertionError:
                if "in use" in replay.stderr():
                    continue
                raise
            with gpsd_watching(f"tcp://127.0.0.1:{nmea_port}") as gpsd:
                deadline = time.monotonic() + HANG_S
                while True:
                    assert time.monotonic() < deadline, f"hung: {len(tpv)} TPV, {gpsd.output()}"
                    ended = replay.proc.poll() is not None
                    got = gpsd.messages(1.0)
                    tpv += [m for m in got if m.get("class") == "TPV" and m.get("mode") == 3]
                    if ended and not got:  # the stream is over and gpsd has said it all
                        break
            run = replay.finish()
        assert run.rc == 0, run.stderr[-2000:]
        break
    with_speed = [m for m in tpv if "speed" in m]
    assert len(with_speed) >= 20, (len(tpv), tpv[-3:])
    assert max(m["speed"] for m in with_speed) <= 0.2, [m["speed"] for m in with_speed]


def _write_store(state: Path) -> None:
    from service.core.ephemeris import EphemerisStore
    from service.sim.keplerian import table1_ephemerides

    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")


def _wait(pred: Callable[[], Any], what: str) -> None:
    """Until ``pred()``; only a hung run (``HANG_S``) fails here."""
    deadline = time.monotonic() + HANG_S
    while not pred():
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        time.sleep(0.01)


def _records(path: Path) -> list[dict]:
    """The whole JSON lines written so far."""
    if not path.exists():
        return []
    text = path.read_text()
    return [json.loads(line) for line in text.splitlines()[: text.count("\n")]]


def _has_fix(path: Path, tow_s: float) -> bool:
    """Whether the daemon has written its FIX record for the epoch at ``tow_s`` (or later)."""
    return any(r["class"] == "FIX" and r["gpst_tow_s"] >= tow_s - 1e-6 for r in _records(path))


def _logged(path: Path, text: str) -> int:
    return path.read_text(errors="replace").count(text) if path.exists() else 0


def test_daemon_reads_ubx_from_a_pty_and_survives_the_writer_going_away(tmp_path):
    """Real pty pair, pyserial in the daemon; the writer closes and comes back. Epochs are
    written once the daemon reads (its "bdsfix running" line) and, after the replug, once it
    has reopened the device: the first epoch written then gives a fix."""
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config
    from service.sim.simulator import Simulator

    state = tmp_path / "state"
    state.mkdir()
    _write_store(state)
    link = tmp_path / "ttyBDS"
    jsonl = tmp_path / "fixes.jsonl"
    err = tmp_path / "daemon.err"
    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=30.0))
    epochs = list(sim.ubx_epochs())
    tow_back = epochs[150][0].tag_gpst_tow_s

    fds: dict[str, int] = {}

    def plug() -> None:
        master, slave = os.openpty()
        fds["master"], fds["slave"] = master, slave
        tmp = tmp_path / "ttyBDS.new"
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(link)

    def unplug() -> None:
        link.unlink()
        os.close(fds["master"])
        os.close(fds["slave"])

    plug()
    argv = [*BDSFIX, "run", "--source", str(link), "--state-dir", str(state)]
    argv += ["--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(jsonl), "--log-level", "info"]
    with err.open("wb") as err_fh:
        proc = subprocess.Popen(argv, cwd=ROOT, stderr=err_fh)
    try:
        _wait(lambda: _logged(err, "bdsfix running") > 0, "start of the daemon")
        for i, (ep, data) in enumerate(epochs):
            if i == 150:
                # all that was written has been read: the unplug cuts no epoch short
                _wait(lambda: _has_fix(jsonl, epochs[149][0].tag_gpst_tow_s), "fix 149")
                n_back = _logged(err, "reconnected after")
                unplug()
                time.sleep(1.0)  # the outage
                plug()
                _wait(lambda n=n_back: _logged(err, "reconnected after") > n, "reopen")
            os.write(fds["master"], data)
            time.sleep(0.02)
        _wait(lambda: _has_fix(jsonl, ep.tag_gpst_tow_s), "the last fix")
    finally:
        proc.terminate()
        proc.communicate(timeout=HANG_S)
        unplug()
    log = err.read_text(errors="replace")
    assert proc.returncode == 0, log[-2000:]
    fixes = [r for r in _records(jsonl) if r["class"] == "FIX"]
    assert sum(f["mode"] == "fast" for f in fixes) > 10
    assert sum(f["mode"] == "spp" for f in fixes) > 10
    # the first epoch written after the daemon reopened the device gives a fix
    back = [f for f in fixes if abs(f["gpst_tow_s"] - tow_back) < 1e-6]
    assert any(f["mode"] != "none" for f in back), back


def test_daemon_sighup_reopens_outputs_and_sigterm_saves_the_store(tmp_path):
    """logrotate-style: rename the JSONL, SIGHUP, and records continue in a new file;
    SIGTERM ends with exit 0 and an intact ephemeris store."""
    import signal

    from service.core.ephemeris import EphemerisStore
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config
    from service.sim.simulator import Simulator

    state = tmp_path / "state"
    state.mkdir()
    _write_store(state)
    jsonl = tmp_path / "fixes.jsonl"
    rotated = tmp_path / "fixes.jsonl.1"
    epochs = list(Simulator(table1_ephemerides(0.0), scenario_config(duration_s=8.0)).ubx_epochs())
    master, slave = os.openpty()
    err = tmp_path / "daemon.err"
    argv = [*BDSFIX, "run", "--source", os.ttyname(slave), "--state-dir", str(state)]
    argv += ["--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(jsonl), "--log-level", "info"]
    with err.open("wb") as err_fh:
        proc = subprocess.Popen(argv, cwd=ROOT, stderr=err_fh)
    try:
        _wait(lambda: _logged(err, "bdsfix running") > 0, "start of the daemon")
        for i, (ep, data) in enumerate(epochs):
            os.write(master, data)
            time.sleep(0.03)
            if i == 40:
                _wait(lambda t=ep.tag_gpst_tow_s: _has_fix(jsonl, t), "fix 40")
                jsonl.rename(rotated)
                proc.send_signal(signal.SIGHUP)
        _wait(lambda: _has_fix(jsonl, ep.tag_gpst_tow_s), "the last fix in the new file")
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, err.read_text(errors="replace")[-2000:]
    old = rotated.read_text().splitlines()
    new = jsonl.read_text().splitlines()
    assert len(old) > 10 and len(new) > 10
    assert json.loads(new[-1])["gpst_tow_s"] > json.loads(old[-1])["gpst_tow_s"]
    assert len(EphemerisStore.load(state / "ephemeris.json")) == 14
