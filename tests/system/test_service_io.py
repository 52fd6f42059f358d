"""The service with real peers: a ZeroMQ SUB socket, gpsd as an NMEA client, and the daemon
reading UBX from a pseudo-terminal through pyserial."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import zmq

from tests.support.paths import DATA, ROOT

HK = DATA / "hksc-2021"
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


def test_zmq_subscriber_gets_valid_fix_track_status(tmp_path):
    port = _free_port()
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(f"tcp://127.0.0.1:{port}")
    proc = subprocess.Popen(
        [
            *BDSFIX,
            "replay",
            str(HK / "hksc1610.obs"),
            "--nav",
            str(HK / "hksc1610.nav"),
            "--restart-at",
            "3",
            "--speed",
            "8",
            "--zmq",
            f"tcp://127.0.0.1:{port}",
            "--status-interval-s",
            "0.5",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
    )
    seen: dict[str, int] = {}
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if sub.poll(500):
                topic, body = sub.recv_multipart()
                rec = json.loads(body)
                _valid(topic.decode(), rec)
                seen[topic.decode()] = seen.get(topic.decode(), 0) + 1
            elif proc.poll() is not None:
                break
    finally:
        proc.kill()
        proc.wait()
        sub.close(0)
    assert seen.get("FIX", 0) > 100 and seen.get("TRACK", 0) >= 16 and seen.get("STATUS", 0) >= 1
    assert seen.get("SKY", 0) > 100


def test_gpsd_reports_our_fixes_as_tpv_mode_3(tmp_path):
    assert shutil.which("gpsd"), "gpsd (Debian package, installed by .ci/run) is required"
    nmea_port, gpsd_port = _free_port(), _free_port()
    jsonl = tmp_path / "fixes.jsonl"
    replay = subprocess.Popen(
        [
            *BDSFIX,
            "replay",
            str(HK / "hksc1610.obs"),
            "--nav",
            str(HK / "hksc1610.nav"),
            "--speed",
            "4",
            "--nmea-tcp",
            f"127.0.0.1:{nmea_port}",
            "--jsonl-out",
            str(jsonl),
        ],
        cwd=ROOT,
        stderr=subprocess.DEVNULL,
    )
    time.sleep(1.0)
    gpsd = subprocess.Popen(
        ["gpsd", "-N", "-n", "-G", "-S", str(gpsd_port), f"tcp://127.0.0.1:{nmea_port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    tpv = []
    try:
        for _ in range(50):
            try:
                client = socket.create_connection(("127.0.0.1", gpsd_port), timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        client.sendall(b'?WATCH={"enable":true,"json":true};\n')
        client.settimeout(1.0)
        buf = b""
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(tpv) < 40:
            try:
                chunk = client.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                break
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                msg = json.loads(line)
                # gpsd can report a mode-3 TPV before its cycle has a date
                # (GGA carries only time of day); only timed reports are matched.
                if msg.get("class") == "TPV" and msg.get("mode") == 3 and "time" in msg:
                    tpv.append(msg)
        client.close()
    finally:
        gpsd.terminate()
        replay.terminate()
        gpsd.wait(5)
        replay.wait(5)
    assert len(tpv) >= 20
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


def _write_store(state: Path) -> None:
    from service.core.ephemeris import EphemerisStore
    from service.sim.keplerian import table1_ephemerides

    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")


def test_daemon_reads_ubx_from_a_pty_and_survives_the_writer_going_away(tmp_path):
    """Real pty pair, pyserial in the daemon; the writer closes and comes back."""
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config
    from service.sim.simulator import Simulator

    state = tmp_path / "state"
    state.mkdir()
    _write_store(state)
    link = tmp_path / "ttyBDS"
    jsonl = tmp_path / "fixes.jsonl"
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
    proc = subprocess.Popen(
        [
            *BDSFIX,
            "run",
            "--source",
            str(link),
            "--state-dir",
            str(state),
            "--nmea-tcp",
            "",
            "--zmq",
            "",
            "--jsonl-out",
            str(jsonl),
            "--log-level",
            "info",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
    )
    t_back = t_seen = None

    def resumed() -> bool:
        for line in jsonl.read_text().splitlines() if jsonl.exists() else []:
            r = json.loads(line)
            if r["class"] == "FIX" and r["mode"] != "none" and r["gpst_tow_s"] >= tow_back - 1e-6:
                return True
        return False

    try:
        time.sleep(1.5)
        for i, (_ep, data) in enumerate(epochs):
            if i == 150:
                unplug()
                time.sleep(1.0)
                plug()
                t_back = time.monotonic()
            os.write(fds["master"], data)
            time.sleep(0.02)
            if t_back is not None and t_seen is None and resumed():
                t_seen = time.monotonic()
        time.sleep(1.0)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
        unplug()
    assert proc.returncode == 0, err.decode()[-2000:]
    recs = [json.loads(x) for x in jsonl.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX"]
    assert sum(f["mode"] == "fast" for f in fixes) > 10
    assert sum(f["mode"] == "spp" for f in fixes) > 10
    # fixes resume after the replug: epochs after index 150 reached the engine
    assert any(
        r["gpst_tow_s"] > fixes[0]["gpst_tow_s"] + 16.0 and r["mode"] != "none" for r in fixes
    )
    assert t_back is not None and t_seen is not None
    print(f"fixes resumed {t_seen - t_back:.2f} s after the device came back")
    assert t_seen - t_back < 2.0


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
    chunks = [
        d
        for _e, d in Simulator(
            table1_ephemerides(0.0), scenario_config(duration_s=8.0)
        ).ubx_epochs()
    ]
    master, slave = os.openpty()
    proc = subprocess.Popen(
        [
            *BDSFIX,
            "run",
            "--source",
            os.ttyname(slave),
            "--state-dir",
            str(state),
            "--nmea-tcp",
            "",
            "--zmq",
            "",
            "--jsonl-out",
            str(jsonl),
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
    )
    try:
        time.sleep(1.5)
        for i, data in enumerate(chunks):
            os.write(master, data)
            time.sleep(0.03)
            if i == 40:
                jsonl.rename(rotated)
                proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, err.decode()[-2000:]
    old = rotated.read_text().splitlines()
    new = jsonl.read_text().splitlines()
    assert len(old) > 10 and len(new) > 10
    assert json.loads(new[-1])["gpst_tow_s"] > json.loads(old[-1])["gpst_tow_s"]
    assert len(EphemerisStore.load(state / "ephemeris.json")) == 14
