"""`bdsfix run` with ephemerides from the network: no nav file, the virtual receiver on a pty
(no ephemeris in its stream) and a real NTRIP caster on loopback (pygnssutils' caster, in a
process of its own, serving RTCM 1042 built from the HKSC broadcast nav).

Everything is judged in data time (the FIX records' ``since_start_s``) or by counts (STATUS
counters, log lines); wall-clock timeouts only stop a hung run.
"""

from __future__ import annotations

import base64
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from service.core.ephemeris import EphemerisStore, ephemeris_problem
from service.core.timebase import bdt_to_gpst, diff_s
from service.core.types import Ephemeris
from service.sim.rtcm import broadcast_sets, frame_1042
from service.sim.scenario import default_start_gpst
from service.sim.simulator import SimConfig, Simulator
from tests.support.ntrip_caster import Caster
from tests.support.paths import DATA, ROOT
from tests.support.replay import HANG_S, LiveReplay

HK_NAV = DATA / "hksc-2021" / "hksc1610.nav"
HONG_KONG = (22.3, 114.2, 50.0)
USER, PASSWORD = "bdsfix-user", "s3cret-pa55"
RIGHT_PASSWORD = "the-right-one"  # noqa: S105
RATE_HZ = 10.0
FIRST_FAST_FIX_S = 1.5
"""Issue 13: the first fast fix within 1.5 s (data time) of the stream's start."""
BACKOFF_MAX_S = 5.0
"""Issue 13: the daemon tries the caster again at least this often."""


def _hksc() -> tuple[list[Ephemeris], Any]:
    from drivers.rinex import read_nav

    data = read_nav(HK_NAV)
    ephs = [e for sets in data.ephemerides.values() for e in sets if ephemeris_problem(e) is None]
    return ephs, data.iono_bds


def _scene(tmp_path: Path, duration_s: float) -> tuple[Simulator, Path, list[Ephemeris]]:
    """The virtual receiver at Hong Kong (HKSC nav, 10 min after a common t_oe, as
    ``bdsfix simulate --nav``) and the caster's file: RTCM 1042 of the set nearest the
    start for every satellite of the nav file; returns the simulator, the file, its sets."""
    ephs, iono = _hksc()
    week, tow = default_start_gpst(ephs)
    lat, lon, alt = HONG_KONG
    cfg = SimConfig(
        lat_deg=lat,
        lon_deg=lon,
        alt_m=alt,
        start_gpst_week=week,
        start_gpst_tow_s=tow,
        duration_s=duration_s,
        rate_hz=RATE_HZ,
    )
    sim = Simulator(ephs, cfg, iono)
    sets = broadcast_sets(ephs, sorted({e.prn for e in ephs}), week, tow)
    path = tmp_path / "hksc-1042.rtcm"
    path.write_bytes(b"".join(frame_1042(e) for e in sets))
    return sim, path, sets


def _records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    text = path.read_text()
    return [json.loads(line) for line in text.splitlines()[: text.count("\n")]]


def _fix_at(path: Path, tow_s: float) -> dict | None:
    for r in _records(path):
        if r["class"] == "FIX" and abs(r["gpst_tow_s"] - tow_s) < 1e-6:
            return r
    return None


def _wait(pred: Callable[[], Any], what: str, run: LiveReplay) -> None:
    deadline = time.monotonic() + HANG_S
    while not pred():
        assert run.proc.poll() is None, f"the daemon ended before {what}:\n{run.stderr()[-3000:]}"
        assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
        run._pump(20)


def _secrets() -> list[str]:
    token = base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()
    return [USER, PASSWORD, token]


def _run_args(slave: int, nav: str, state: Path, jsonl: Path) -> list[str]:
    """``bdsfix run`` on the pty with the caster as its only nav source, JSONL out, debug logs."""
    return [
        "run",
        "--source",
        os.ttyname(slave),
        "--nav",
        nav,
        "--state-dir",
        str(state),
        "--nmea-tcp",
        "",
        "--jsonl-out",
        str(jsonl),
        "--log-level",
        "debug",
    ]


def test_run_with_ntrip_nav_only_fast_fix_then_caster_restart(tmp_path):
    """No nav file, no ephemeris in the receiver's stream, the caster serving 1042: the
    daemon's first fast fix comes within 1.5 s of the stream's start (data time). The caster
    is then killed (SIGKILL) and started again while the receiver streams on: every epoch
    of the outage is fixed from the store the daemon kept, it reconnects (counted, its
    backoff never above 5 s), takes the caster's sets again as repeats, and saves them at
    SIGTERM. At debug level, no log line carries the user, the password or their base64."""
    sim, rtcm, sets = _scene(tmp_path, duration_s=30.0)
    n_sets = len(sets)
    epochs = list(sim.ubx_epochs())
    # sets of satellites the nav file holds no current set for (t_oe more than the default
    # ntrip_max_age_s, 2 h, from the start): the daemon must refuse these as stale
    t0 = (epochs[0][0].tag_gpst_week, epochs[0][0].tag_gpst_tow_s)
    stale = {e.prn for e in sets if abs(diff_s(*t0, *bdt_to_gpst(e.week, e.toe_sow_s))) > 7200}
    state = tmp_path / "state"
    jsonl = tmp_path / "fixes.jsonl"
    master, slave = os.openpty()
    with (
        Caster(
            rtcm, user=USER, password=PASSWORD, cycle_s=1.0, log_path=tmp_path / "caster.log"
        ) as caster,
        LiveReplay(
            _run_args(slave, caster.url(USER, PASSWORD), state, jsonl),
            topics=(b"STATUS",),
        ) as run,
    ):
        # The stream starts once the daemon holds a whole cycle of the caster's sets.
        run.wait_status(
            lambda s: s["counters"].get("ntrip_ephemerides_rtcm", 0) >= n_sets,
            "a whole cycle of the caster's ephemerides",
        )
        kill_at, back_at = 100, 160
        for i, (ep, data) in enumerate(epochs):
            if i == kill_at:
                _wait(lambda t=epochs[i - 1][0].tag_gpst_tow_s: _fix_at(jsonl, t), "fix", run)
                caster.kill()
                _wait(lambda: "disconnected" in run.stderr(), "the disconnect", run)
            if i == back_at:
                # the outage lasted at least 60 epochs of stream: all read and solved
                _wait(lambda t=epochs[i - 1][0].tag_gpst_tow_s: _fix_at(jsonl, t), "fix", run)
                caster.start()
                _wait(lambda: "reconnected after" in run.stderr(), "the reconnection", run)
                repeats = run.wait_status(lambda s: True, "a STATUS")["counters"]["ntrip_repeats"]
            os.write(master, data)
            time.sleep(0.02)
        last_tow = ep.tag_gpst_tow_s
        _wait(lambda: _fix_at(jsonl, last_tow), "the last fix", run)
        run.wait_status(
            lambda s: s["counters"]["ntrip_repeats"] >= repeats + n_sets,
            "a whole cycle of the restarted caster's sets, as repeats",
        )
        run.proc.terminate()
        result = run.finish()
    os.close(master)
    os.close(slave)
    log = result.stderr
    assert result.rc == 0, log[-3000:]
    fixes = [r for r in _records(jsonl) if r["class"] == "FIX"]
    assert len(fixes) == len(epochs)
    first_fast = next(f for f in fixes if f["mode"] == "fast")
    print(f"first fast fix at {first_fast['since_start_s']:.2f} s of stream (data time)")
    assert first_fast["since_start_s"] <= FIRST_FAST_FIX_S
    # the caster's outage: every epoch of it fixed from the store the daemon kept
    outage = fixes[kill_at:back_at]
    assert all(f["mode"] in ("fast", "spp") for f in outage), [f["mode"] for f in outage]
    c = result.final["counters"]
    assert "source_ephemerides_rtcm" not in c  # nothing came from the receiver's stream
    assert c["ntrip_reconnects"] >= 1 and c["ntrip_connects"] >= 2
    assert c["ntrip_ephemerides"] == c["ephemeris_ntrip"] > 0
    assert c.get("ntrip_stale", 0) == len(stale)
    assert c["ntrip_ephemerides"] + len(stale) == n_sets
    refused = set(re.findall(r"ephemeris (C\d\d) \(BDT week \d+, t_oe \d+ s\) is [0-9.]+ h", log))
    assert refused == stale
    retries = [float(x) for x in re.findall(r"cannot open \([^)]*\); retry in ([0-9.]+) s", log)]
    print(
        f"network sets taken {c['ntrip_ephemerides']}, stale {c.get('ntrip_stale', 0)}, "
        f"repeats {c['ntrip_repeats']}, connects {c['ntrip_connects']}, reconnects "
        f"{c['ntrip_reconnects']}, retries while down {retries}"
    )
    assert retries, "no retry while the caster was down"
    assert max(retries) <= BACKOFF_MAX_S
    for secret in _secrets():
        assert secret not in log
        assert secret not in (tmp_path / "fixes.jsonl").read_text()
    saved = EphemerisStore.load(state / "ephemeris.json")
    assert len(saved) == c["ephemeris_ntrip"]


def test_run_with_wrong_ntrip_credentials_says_so_in_one_line_and_reads_on(tmp_path):
    """A caster that refuses the credentials: one ERROR line naming the URL redacted and
    what to do; the caster is not asked again; the daemon goes on reading its receiver and
    stops with 0 at SIGTERM (documented in README and docs/architecture.md)."""
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config

    _sim, rtcm, _sets = _scene(tmp_path, duration_s=1.0)
    state = tmp_path / "state"
    state.mkdir()
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")  # warm: the receiver alone gives fixes
    epochs = list(Simulator(table1_ephemerides(0.0), scenario_config(duration_s=3.0)).ubx_epochs())
    jsonl = tmp_path / "fixes.jsonl"
    master, slave = os.openpty()
    with (
        Caster(rtcm, user=USER, password=RIGHT_PASSWORD) as caster,
        LiveReplay(_run_args(slave, caster.url(USER, PASSWORD), state, jsonl)) as run,
    ):
        _wait(lambda: "refused the credentials" in run.stderr(), "the refusal", run)
        for _ep, data in epochs:
            os.write(master, data)
            time.sleep(0.01)
        _wait(lambda: _fix_at(jsonl, epochs[-1][0].tag_gpst_tow_s), "the last fix", run)
        run.proc.terminate()
        result = run.finish()
    os.close(master)
    os.close(slave)
    assert result.rc == 0, result.stderr[-3000:]
    lines = [ln for ln in result.stderr.splitlines() if "refused the credentials" in ln]
    assert len(lines) == 1, lines
    assert "ERROR" in lines[0] and "ntrip://***@127.0.0.1:" in lines[0]
    assert result.final["counters"]["ntrip_refused"] == 1
    assert result.final["counters"].get("ntrip_connects", 0) == 0
    for secret in _secrets():
        assert secret not in result.stderr
    fixes = [r for r in _records(jsonl) if r["class"] == "FIX"]
    assert sum(f["mode"] != "none" for f in fixes) > len(epochs) // 2


def test_malformed_ntrip_url_is_one_line_exit_2_without_the_password(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "service",
            "run",
            "--source",
            str(tmp_path / "nothing-yet"),
            "--nav",
            f"ntrip://{USER}:{PASSWORD}@caster.example:2101",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert "no mountpoint" in lines[0] and "ntrip://***@caster.example:2101" in lines[0]
    for secret in _secrets():
        assert secret not in proc.stderr


@pytest.mark.parametrize(
    "url",
    [
        f"ntrips://{USER}:{PASSWORD}@caster.example:2101/EPH",
        f"http://{USER}:{PASSWORD}@caster.example:2101/EPH",
        f"ntrip:{USER}:{PASSWORD}@caster.example:2101/EPH",
        f"ntrip://{USER}:{PASSWORD}\nline2@caster.example:99999/EPH",
    ],
    ids=["ntrips", "http", "no-slashes", "newline"],
)
@pytest.mark.parametrize("command", ["run", "solve"])
def test_a_url_of_any_scheme_is_refused_in_one_line_without_the_password(url, command):
    """Issue 23: with a scheme other than exactly ``ntrip://`` the error printed the password
    (the entry was opened as a nav file); a password with a newline was printed whole."""
    obs = str(HK_NAV.with_suffix(".obs"))
    argv = ["run", "--source", obs, "--nav", url] if command == "run" else ["solve", obs, url]
    proc = subprocess.run(
        [sys.executable, "-m", "service", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    for secret in [*_secrets(), "line2"]:
        assert secret not in proc.stderr + proc.stdout


@pytest.mark.parametrize(
    "argv",
    [
        ["replay", str(HK_NAV.with_suffix(".obs")), "--nav", "NAV"],
        ["solve", str(HK_NAV.with_suffix(".obs")), "NAV"],
        ["ttff", str(HK_NAV.with_suffix(".obs")), "NAV", "--trials", "1"],
        ["simulate", "--nav", "NAV", "--out", "-"],
    ],
    ids=lambda a: a[0],
)
def test_the_other_commands_take_no_ntrip_nav_and_do_not_show_it(argv):
    url = f"ntrip://{USER}:{PASSWORD}@caster.example:2101/EPH"
    proc = subprocess.run(
        [sys.executable, "-m", "service", *[url if a == "NAV" else a for a in argv]],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "read by 'bdsfix run'" in lines[0], lines
    for secret in _secrets():
        assert secret not in proc.stderr + proc.stdout
