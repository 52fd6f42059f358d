"""Crash safety of the persisted ephemeris store: SIGKILL during writes, 100 times.

Most kills hit a forked child that saves the store in a tight loop (alternating two
different contents, so a torn or mixed file would show); the rest hit the real daemon
(``bdsfix run`` with ``--nav`` and ``--store-save-interval-s 0``, which saves after every
ephemeris it takes in: a burst of writes at start-up, which its writer thread folds into a
few). After every kill the store must load
intact with one of the contents that were written, and the next daemon start must warm-start
from it. Temp files a kill leaves behind are removed by the next save.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from service.commands.run import load_store
from service.core.ephemeris import EphemerisStore
from service.core.types import Ephemeris
from tests.support.paths import DATA

NAV = DATA / "hksc-2021" / "hksc1610.nav"
BDSFIX = str(Path(sys.executable).parent / "bdsfix")
KILLS_CHILD = 85
KILLS_DAEMON = 15
HANG_S = 60.0  # waits for an event end only a hung run


def _keys(store: EphemerisStore) -> set[tuple[str, int, float]]:
    return {(e.prn, e.week, e.toe_sow_s) for e in store.all()}


def _temp_files(state: Path) -> list[Path]:
    return list(state.glob(".ephemeris.json.*"))


def _save_forever(a: EphemerisStore, b: EphemerisStore, path: Path, ready_w: int) -> None:
    """Child: alternate two stores into ``path`` until killed."""
    try:
        os.write(ready_w, b"x")
        while True:
            a.save(path)
            b.save(path)
    finally:
        os._exit(1)


def test_sigkill_during_store_writes_never_leaves_a_torn_store(tmp_path):
    from drivers.rinex import read_nav

    nav = read_nav(NAV)
    a = EphemerisStore()
    for items in nav.ephemerides.values():
        a.add_all(items)
    a.iono = nav.iono_bds
    b = EphemerisStore()
    b.add_all(a.all()[::2])
    assert len(a) > 50 and len(b) < len(a)
    contents = {frozenset(_keys(a)), frozenset(_keys(b))}
    state = tmp_path / "state"
    path = state / "ephemeris.json"
    a.save(path)
    rng = random.Random(5)
    mid_write = 0
    for _ in range(KILLS_CHILD):
        ready_r, ready_w = os.pipe()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - child
            os.close(ready_r)
            _save_forever(a, b, path, ready_w)
        os.close(ready_w)
        assert os.read(ready_r, 1) == b"x"
        os.close(ready_r)
        time.sleep(rng.uniform(0.0, 0.03))
        os.kill(pid, signal.SIGKILL)
        _, status = os.waitpid(pid, 0)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
        debris = _temp_files(state)
        assert len(debris) <= 1, debris  # the previous kill's debris was cleaned up
        mid_write += bool(debris)
        back = load_store(state, 7200.0)  # the daemon's warm start
        assert frozenset(_keys(back)) in contents
        assert back.iono in (a.iono, None)
    print(f"{KILLS_CHILD} kills of a saving child, {mid_write} left a temp file (mid-write)")
    assert mid_write >= KILLS_CHILD // 4  # the kills did land during writes
    a.save(path)
    assert not _temp_files(state)


def _stop_mid_write(
    proc: subprocess.Popen[str], state: Path, debris: set[Path], n_all: int, deadline: float
) -> None:
    """SIGSTOP the daemon while a temp file of its own exists (checked once it is stopped),
    so the kill that follows lands mid-write whatever the machine's speed; if the burst
    ends first (the store holds all ``n_all`` sets) it stays running."""
    while time.monotonic() < deadline and proc.poll() is None:
        if set(_temp_files(state)) - debris:
            proc.send_signal(signal.SIGSTOP)
            if set(_temp_files(state)) - debris:
                return
            proc.send_signal(signal.SIGCONT)
        elif len(EphemerisStore.load(state / "ephemeris.json")) >= n_all:
            return
        time.sleep(0.0005)


def _daemon(state: Path, tty: str) -> subprocess.Popen[str]:
    argv = [BDSFIX, "run", "--source", tty, "--nav", str(NAV), "--state-dir", str(state)]
    argv += ["--nmea-tcp", "", "--zmq", "", "--store-save-interval-s", "0", "--log-level", "info"]
    return subprocess.Popen(argv, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)


def test_sigkill_of_the_daemon_while_it_saves_then_warm_start(tmp_path):
    from service.sim.keplerian import table1_ephemerides

    state = tmp_path / "state"
    seed = EphemerisStore()
    seed.add_all(table1_ephemerides(0.0))
    seed.save(state / "ephemeris.json")
    n_seed = len(seed)
    # the sets of the nav file a store takes: every system's (the daemon's default), less
    # the GPS/Galileo sets the file marks unhealthy (E18, G11), which the store refuses
    nav_store = EphemerisStore()
    for ephs in _nav_ephemerides().values():
        nav_store.add_all(ephs)
    n_nav = len(nav_store)
    master, slave = os.openpty()  # an idle receiver: the daemon only writes its store
    rng = random.Random(7)
    mid_write = 0
    try:
        for i in range(KILLS_DAEMON + 1):
            before = (state / "ephemeris.json").stat().st_mtime_ns
            debris = set(_temp_files(state))
            proc = _daemon(state, os.ttyname(slave))
            deadline = time.monotonic() + HANG_S
            while (state / "ephemeris.json").stat().st_mtime_ns == before and not (
                set(_temp_files(state)) - debris
            ):  # wait until the write burst has begun
                assert proc.poll() is None and time.monotonic() < deadline
                time.sleep(0.002)
            if i < KILLS_DAEMON and i % 2 == 0:  # aimed: stopped mid-write, then killed
                _stop_mid_write(proc, state, debris, n_seed + n_nav, deadline)
                proc.kill()
            elif i < KILLS_DAEMON:  # anywhere in the burst
                time.sleep(rng.uniform(0.0, 0.15))
                proc.kill()
            else:  # the last start takes in the whole nav file, then stops cleanly
                while len(EphemerisStore.load(state / "ephemeris.json")) < n_seed + n_nav:
                    assert proc.poll() is None and time.monotonic() < deadline
                    time.sleep(0.05)
                proc.terminate()
            _, err = proc.communicate(timeout=HANG_S)
            mid_write += i < KILLS_DAEMON and bool(_temp_files(state))
            assert "Traceback" not in err, err
            assert "starting with an empty store" not in err, err
            assert "warm start:" in err, err  # loaded the store the previous kill left
            warm = int(err.split("warm start: ")[1].split()[0])
            assert warm >= n_seed
            back = EphemerisStore.load(state / "ephemeris.json")
            assert len(back) >= n_seed
        assert proc.returncode == 0
    finally:
        os.close(master)
        os.close(slave)
    print(f"{KILLS_DAEMON} kills of the daemon, {mid_write} left a temp file (mid-write)")
    assert mid_write >= 1  # the aimed kills landed while a temp file was being written
    assert len(back) == n_seed + n_nav
    assert not _temp_files(state)


def _nav_ephemerides() -> dict[str, list[Ephemeris]]:
    """The nav file's sets of every system, as the daemon reads it by default."""
    from drivers.rinex import read_nav

    return {k: list(v) for k, v in read_nav(NAV, ("C", "G", "E")).ephemerides.items()}
