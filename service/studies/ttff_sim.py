"""``bdsfix ttff --simulate``: time to first fix of the whole stream path, on restarts of a
virtual receiver.

The virtual receiver (:mod:`service.sim.simulator`) writes UBX into one end of a real pty pair;
``bdsfix run`` reads the other end through pyserial (driver -> frame-sync tracker -> engine
-> JSONL), exactly as on a receiver host. The stream is a sequence of trials: at each
trial's start the receiver restarts (all tracking lost, ephemerides held: a warm start), so
every satellite is re-acquired after a random delay, reaches bit sync after another, waits
for the next preamble, and its RAWX pseudorange becomes valid once that subframe's SOW has
decoded (the SOW-decode rule, :mod:`service.core.sow_rule`: D2 0.12 s, D1 1.2 s into the
subframe; ``--full-rule subframe``: at its end, 0.6 s / 6 s), boundaries from BDT as in the
real signal. The daemon trusts the receiver's prMes, so the same rule times the fast and the
conventional fix. Between trials the receiver is silent for a
random 0.5-6.5 s, so restarts fall at random phases of the D1 subframe.

The stream goes as fast as the daemon reads it (the pty's flow control paces it); every time
below is data time since the trial's restart, as a receiver running in real time would see.

From the daemon's JSONL:
- TTFF_fast: the first epoch with a published fix of the fast solver (``mode`` fast);
- TTFF_conventional: the first epoch at which the satellites the daemon holds as full (its
  ``TRACK`` full events since the restart) give, from their full pseudoranges alone, an SPP
  fix with PDOP <= 10;
- geo_only: the first epoch with >= 4 full GEOs, solved by SPP from the GEOs alone; its
  error is against the true position.
Every fast fix is compared with an SPP solved from the same epoch's full pseudoranges of
every tracked satellite (the simulator knows them, the receiver does not yet): they must
agree to 1 mm (paper eq. 16: with the integers right, the fast fix is the SPP fix). Its
error against the true position is reported as a ratio to sigma * PDOP.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tty
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from service.core.bds import is_geo
from service.core.ephemeris import EphemerisStore
from service.core.errors import BdsfixError
from service.core.settings import flags_of
from service.core.timebase import diff_s, gpst_to_bdt, normalize
from service.core.types import Ephemeris, KlobucharParams, MeasurementEpoch
from service.engine.solver import IonoSet, SolverConfig, solve
from service.sim.simulator import SimConfig, SimEpoch, Simulator

log = logging.getLogger(__name__)

PDOP_CONVENTIONAL_MAX = 10.0
FAST_VS_SPP_MAX_M = 1e-3


@dataclass(frozen=True, slots=True)
class SimTrialPlan:
    """One restart of the virtual receiver: when, with which seed and clock offset."""

    index: int
    start_gpst_week: int
    start_gpst_tow_s: float
    seed: int
    clock_offset_s: float


@dataclass(frozen=True, slots=True)
class SimTrial:
    """What one restart gave, in data seconds since the restart."""

    index: int
    fast_s: float | None
    conventional_s: float | None
    geo_only_s: float | None
    geo_only_err_m: float | None
    fast_fixes: int
    fast_vs_spp_m: float | None  # the largest |fast - SPP| of the trial's fast fixes
    # (a coarse-time fix with no full row is left out: it is not SPP at the true time)
    max_err_ratio: float | None  # 3D error / (sigma * PDOP), over the trial's fast fixes
    declined: dict[str, int] = field(default_factory=dict)  # reasons before the first fix
    first_method: str | None = None  # the first fast fix's method (coarse_time, or None)
    coarse_no_full_vs_spp_m: float | None = None  # coarse-time fixes with no full row
    coarse_full_vs_spp_m: float | None = None  # coarse-time fixes with a full row (in fast_vs)


def plan_trials(
    start_gpst_week: int, start_gpst_tow_s: float, trials: int, trial_s: float, seed: int
) -> list[SimTrialPlan]:
    """Consecutive restarts separated by a random silent gap of 0.5-6.5 s.

    Starts are whole milliseconds and clock offsets whole microseconds, so that every
    receiver time tag is a whole microsecond (the JSONL carries six decimals)."""
    rng = np.random.default_rng(seed)
    out = []
    week, tow = normalize(start_gpst_week, round(start_gpst_tow_s, 3))
    for k in range(trials):
        offset_s = round(float(rng.uniform(-0.01, 0.01)), 6)
        out.append(SimTrialPlan(k, week, tow, int(rng.integers(2**31)), offset_s))
        gap_s = round(float(rng.uniform(0.5, 6.5)), 3)
        week, tow = normalize(week, round(tow + trial_s + gap_s, 3))
    return out


def _time_key(week: int, tow_s: float) -> tuple[int, int]:
    """Epoch key in microseconds: every time tag of the stream is a whole microsecond."""
    return int(week), round(tow_s * 1e6)


class SimStream:
    """The trials' simulators; their UBX bytes in order, and the truth of every epoch."""

    def __init__(
        self,
        ephs: Sequence[Ephemeris],
        iono: KlobucharParams | None,
        base: SimConfig,
        plans: Sequence[SimTrialPlan],
        trial_s: float,
        max_eph_age_s: float,
        iono_gps: KlobucharParams | None = None,
    ) -> None:
        self.ephs, self.iono, self.base, self.plans, self.trial_s = ephs, iono, base, plans, trial_s
        self.iono_gps = iono_gps  # GPS/Galileo rows' delay (Simulator)
        self.max_eph_age_s = max_eph_age_s
        self.epochs: dict[tuple[int, int], tuple[int, SimEpoch]] = {}
        self.by_trial: list[list[SimEpoch]] = [[] for _ in plans]
        self.last_key: tuple[int, int] | None = None

    def chunks(self) -> Iterator[bytes]:
        from tqdm import tqdm

        # progress on a terminal only (disable=None), on stderr
        for plan in tqdm(self.plans, desc="ttff restarts", unit="trial", disable=None):
            cfg = SimConfig(
                lat_deg=self.base.lat_deg,
                lon_deg=self.base.lon_deg,
                alt_m=self.base.alt_m,
                start_gpst_week=plan.start_gpst_week,
                start_gpst_tow_s=plan.start_gpst_tow_s,
                duration_s=self.trial_s,
                rate_hz=self.base.rate_hz,
                clock_offset_s=plan.clock_offset_s,
                noise_m=self.base.noise_m,
                seed=plan.seed,
                elmask_deg=self.base.elmask_deg,
                full_rule=self.base.full_rule,
                systems=self.base.systems,
            )
            bw, bs = gpst_to_bdt(plan.start_gpst_week, plan.start_gpst_tow_s)
            # the satellites whose ephemeris the daemon's store accepts (max age |t - toe|)
            age_ok = self.max_eph_age_s
            fresh = [e for e in self.ephs if abs(diff_s(bw, bs, e.week, e.toe_sow_s)) <= age_ok]
            sim = Simulator(fresh, cfg, self.iono, self.iono_gps)
            for ep, data in sim.ubx_epochs():
                key = _time_key(ep.tag_gpst_week, ep.tag_gpst_tow_s)
                self.epochs[key] = (plan.index, ep)
                self.by_trial[plan.index].append(ep)
                self.last_key = key
                yield data


def _write_all(fd: int, chunks: Iterator[bytes], stop: threading.Event) -> None:
    for data in chunks:
        view = memoryview(data)
        while view and not stop.is_set():
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            view = view[n:]
        if stop.is_set():
            return


def run_daemon_on_pty(
    stream: SimStream,
    state_dir: Path,
    jsonl: Path,
    cfg: SolverConfig,
    nav: Sequence[str] = (),
    max_eph_age_s: float = 7200.0,
    timeout_s: float = 900.0,
    coarse_fix: bool = False,
    systems: frozenset[str] = frozenset("C"),
) -> list[dict[str, Any]]:
    """Feed the stream to ``bdsfix run`` through a pty; the records of its JSONL output."""
    master, slave = os.openpty()
    tty.setraw(slave)  # binary from the first byte, before the daemon configures the port
    # A private name for the device: a daemon elsewhere that retries a vanished /dev/pts/N
    # must not open this run's pty when the kernel hands out the same number.
    device = str(state_dir / "ttyBDS")
    os.symlink(os.ttyname(slave), device)
    ready = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ready.bind(str(state_dir / "notify"))
    ready.settimeout(1.0)
    cmd = [
        sys.executable,
        "-m",
        "service.commands.cli",
        "run",
        "--source",
        device,
        "--state-dir",
        str(state_dir),
        "--nmea-tcp",
        "",
        "--zmq",
        "",
        "--jsonl-out",
        str(jsonl),
        "--status-interval-s",
        "5",
        "--max-eph-age-s",
        str(max_eph_age_s),
        *flags_of(cfg),
        # the paper's method and SPP are timed here; the coarse-time fix only when asked
        "--coarse-fix",
        "true" if coarse_fix else "false",
        "--systems",
        ",".join(sorted(systems)),
    ]
    for path in nav:
        cmd += ["--nav", str(path)]
    env = dict(os.environ, NOTIFY_SOCKET=str(state_dir / "notify"))
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env)  # noqa: S603
    stop = threading.Event()
    problem = ""
    try:
        _wait_until_ready(proc, ready, time.monotonic() + 60.0)
        writer = threading.Thread(
            target=_write_all, args=(master, stream.chunks(), stop), daemon=True
        )
        writer.start()
        deadline = time.monotonic() + timeout_s
        while writer.is_alive() and time.monotonic() < deadline and proc.poll() is None:
            writer.join(0.5)
        if writer.is_alive() and proc.poll() is None:
            problem = f"stream not consumed within {timeout_s:g} s"
        # the daemon has read everything; wait until its last epoch is in the JSONL
        last = stream.last_key
        while not problem and time.monotonic() < deadline and proc.poll() is None:
            if last is not None and _has_fix_at(jsonl, last):
                break
            time.sleep(0.2)
        if proc.poll() is not None:
            problem = "bdsfix run stopped early"
    finally:
        stop.set()
        ready.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        os.close(master)
        os.close(slave)
    if problem:
        raise BdsfixError(f"{problem}: {err.strip()[-400:]}")
    if proc.returncode != 0:
        raise BdsfixError(f"bdsfix run exited {proc.returncode}: {err.strip()[-400:]}")
    return [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]


def _wait_until_ready(proc: subprocess.Popen[str], sock: socket.socket, deadline: float) -> None:
    """Block until the daemon reports READY=1 (sd_notify): its port is open and configured,
    so the first byte written is read (a restart is timed from the receiver's first byte)."""
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if b"READY=1" in sock.recv(4096):
                return
        except TimeoutError:
            continue
    raise BdsfixError("bdsfix run did not report READY")


def _has_fix_at(jsonl: Path, key: tuple[int, int]) -> bool:
    try:
        with open(jsonl, "rb") as f:
            f.seek(max(0, os.path.getsize(jsonl) - 65536))
            tail = f.read().decode(errors="replace").splitlines()
    except FileNotFoundError:
        return False
    for line in reversed(tail):
        if '"class":"FIX"' in line:
            try:
                r = json.loads(line)
            except ValueError:
                continue
            if _time_key(r["gpst_week"], r["gpst_tow_s"]) == key:
                return True
    return False


def _spp(
    ep: SimEpoch,
    prns: Sequence[str],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
) -> Any:
    wanted = set(prns)
    idx = [i for i, p in enumerate(ep.prn) if p in wanted]
    m = MeasurementEpoch.from_columns(
        ep.tag_gpst_week,
        ep.tag_gpst_tow_s,
        [ep.prn[i] for i in idx],
        ["2I"] * len(idx),
        ep.pr_m[idx],
        cn0_dbhz=ep.cn0_dbhz[idx],  # the C/N0 the receiver reports: the same weights
    )
    return solve(m, store, iono, cfg, solver="spp")


def analyse(
    stream: SimStream,
    records: list[dict[str, Any]],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    noise_m: float,
) -> list[SimTrial]:
    """Per-trial TTFF and checks from the daemon's records (see the module docstring)."""
    fixes: dict[tuple[int, int], dict[str, Any]] = {}
    full_at: dict[int, list[tuple[tuple[int, int], str]]] = {p.index: [] for p in stream.plans}
    for r in records:
        key = _time_key(r["gpst_week"], r["gpst_tow_s"])
        hit = stream.epochs.get(key)
        if hit is None:
            continue
        if r["class"] == "FIX" and r.get("solver", "fast") == "fast":
            fixes[key] = r
        elif r["class"] == "TRACK" and r["event"] == "full":
            full_at[hit[0]].append((key, r["prn"]))
    out = []
    for plan in stream.plans:
        epochs = stream.by_trial[plan.index]
        if not epochs:
            continue
        truth = epochs[0].truth_x_ecef_m
        full: set[str] = set()
        events = sorted(full_at[plan.index])
        fast = conv = geo = geo_err = None
        n_fast, diffs, ratios, no_full, coarse_full = 0, [], [], [], []
        first_method = None
        # SPP references start at the true position (same least-squares fixed point, fewer
        # iterations); the daemon's fast fix started from the Earth's centre
        ref_cfg = replace(cfg, x0_ecef_m=(float(truth[0]), float(truth[1]), float(truth[2])))
        declined: Counter[str] = Counter()
        for ep in epochs:
            key = _time_key(ep.tag_gpst_week, ep.tag_gpst_tow_s)
            while events and events[0][0] <= key:
                full.add(events.pop(0)[1])
            fix = fixes.get(key)
            if fix is not None and fix["mode"] == "fast":
                n_fast += 1
                if fast is None:
                    fast = ep.t_s
                    first_method = fix.get("method")
                # the rows the daemon had: BeiDou's (full, or fractional from MEASX) and
                # those of other systems with prMes valid (the virtual receiver's MEASX is
                # BeiDou's)
                rows = [p for i, p in enumerate(ep.prn) if p[0] == "C" or ep.full[i]]
                ref = _spp(ep, rows, store, iono, ref_cfg)
                x = np.asarray(fix["x_ecef_m"])
                if ref.ok and ref.x_ecef_m is not None:
                    d = float(np.linalg.norm(x - np.asarray(ref.x_ecef_m)))
                    if fix.get("method") == "coarse_time" and not fix.get("n_full"):
                        no_full.append(d)
                    else:
                        diffs.append(d)
                        if fix.get("method") == "coarse_time":
                            coarse_full.append(d)
                if fix.get("pdop"):
                    err = float(np.linalg.norm(x - truth))
                    ratios.append(err / (noise_m * float(fix["pdop"])))
            elif fix is not None and fix["mode"] == "none" and fast is None and conv is None:
                declined[fix.get("reason", "")] += 1
            if conv is None and len(full) >= 4:
                c = _spp(ep, sorted(full), store, iono, ref_cfg)
                if c.ok and c.pdop is not None and c.pdop <= PDOP_CONVENTIONAL_MAX:
                    conv = ep.t_s
            geos = sorted(p for p in full if is_geo(p))
            if geo is None and len(geos) >= 4:
                # shown for its error: a GEO-only PDOP is far above the published gate
                g = _spp(ep, geos, store, iono, replace(ref_cfg, pdop_max=math.inf))
                if g.ok and g.x_ecef_m is not None:
                    geo = ep.t_s
                    geo_err = float(np.linalg.norm(np.asarray(g.x_ecef_m) - truth))
        out.append(
            SimTrial(
                plan.index,
                fast,
                conv,
                geo,
                geo_err,
                n_fast,
                max(diffs) if diffs else None,
                max(ratios) if ratios else None,
                dict(declined),
                first_method,
                max(no_full) if no_full else None,
                max(coarse_full) if coarse_full else None,
            )
        )
    return out


def summarize_sim(trials: list[SimTrial], location: dict[str, float]) -> dict[str, Any]:
    """The ``ttff --json`` document (docs/architecture.md), with the stream checks added."""
    from service.studies.ttff import summarize

    doc = summarize(trials)
    doc["simulated"] = True
    doc["location"] = location
    doc["fast"]["fixes"] = sum(t.fast_fixes for t in trials)
    ratios = [t.max_err_ratio for t in trials if t.max_err_ratio is not None]
    if ratios:
        doc["fast"]["max_err_over_sigma_pdop"] = round(max(ratios), 3)
    med_f, med_c = doc["fast"].get("median_s"), doc["conventional"].get("median_s")
    if med_f and med_c:
        doc["conventional_over_fast"] = round(med_c / med_f, 2)
    declined: Counter[str] = Counter()
    for t in trials:
        declined.update(t.declined)
    doc["fast"]["declined_before_first_fix"] = dict(declined)
    doc["fast"]["first_by_coarse_time"] = sum(t.first_method == "coarse_time" for t in trials)
    no_full = [t.coarse_no_full_vs_spp_m for t in trials if t.coarse_no_full_vs_spp_m is not None]
    if no_full:
        doc["fast"]["coarse_no_full_max_diff_to_spp_m"] = round(max(no_full), 4)
    c_full = [t.coarse_full_vs_spp_m for t in trials if t.coarse_full_vs_spp_m is not None]
    if c_full:
        doc["fast"]["coarse_full_max_diff_to_spp_m"] = max(c_full)
    doc["per_trial"] = [
        {"fast_s": t.fast_s, "conventional_s": t.conventional_s, "geo_only_s": t.geo_only_s}
        for t in trials
    ]
    return doc
