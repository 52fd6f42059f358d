"""Throughput against RTKLIB: `bdsfix solve` and `rnx2rtkp` side by side on the same files.

Both programs run as whole processes (wall time of the process, start-up included) on the
same RINEX files, alternating (bdsfix, rnx2rtkp, bdsfix, ...) so that load from other jobs
falls on both alike; the medians and their ratio are printed per file, with the 3D RMS
error of each program's fixes against the file's reference position, so that speed is never
bought with accuracy.

RTKLIB is configured as the equivalent of bdsfix's defaults (written by this bench): BDS
only, single point, B1I, 10 deg mask, broadcast ionosphere, Saastamoinen, broadcast
ephemerides, RAIM fault detection and exclusion on (bdsfix tests and excludes by default).

Files:
- HKSC (../shared/data/hksc-2021): 205 epochs at 1 Hz, 5 GEOs; truth the surveyed station.
- TST (../shared/data/hk-tst-urban-2019): 1760 epochs of an urban drive; truth per epoch
  from groundTruth_TST.csv. TST-0: the same without fault exclusion on either side
  (`--max-exclusions 0`, RTKLIB without RAIM FDE; both still test the residuals).
- SIM24: a simulated 24 h, 30 s reference-station day written by this bench (the paper's
  Table 1 constellation as hourly broadcast sets, RINEX 3.04 nav; ranges from
  service.sim.rangegen at the HKSC station with GPS Klobuchar, Saastamoinen and 0.5 m
  noise), solved with --mode both (SIM24) and --mode spp (SIM24s); truth the simulated
  position.
- ONE: HKSC's first epoch alone: the start-up of `bdsfix solve`.
- HKSC-GECs, TST-GECs (``--files hksc-gec,hksc-gec-strict,...``: each needs its base row):
  bdsfix with :data:`STRICT` settings; HKSC-GECa, TST-GECa (``hksc-gec-aided``,
  ``tst-gec-aided``) with :data:`AIDED` (height aiding and the prediction screen).
- SBF-GEC (../shared/data/leuven-septentrio-sbf-2025): 12 epochs of a Septentrio mosaic,
  BDS + GPS + Galileo. bdsfix replays the SBF file (`bdsfix replay --max-speed`, its nav
  blocks the only ephemerides); rnx2rtkp reads the RINEX 3.04 obs and nav that RTKLIB's
  convbin writes from it (``-r sbf``, done once, not timed). Truth: each epoch's
  PVTGeodetic (the receiver's own SBAS-aided fix, metre level). bdsfix reads the BeiDou,
  GPS and Galileo rows and the file's BDSNav/GPSNav/GALNav sets, while RTKLIB 2.4.3's
  convbin writes no BeiDou ephemeris from SBF (rnx2rtkp: GPS and Galileo); SBF-RNX runs
  `bdsfix solve` on convbin's RINEX, the same input as rnx2rtkp.

Rows with a truth per epoch also print the availability (fixes over the epochs with a
truth: 205 HKSC, 485 TST, 300 3GEO, 12 SBF) and each side's 3D error p50/p95/max. 3GEO's
"truth" is rnx2rtkp's own median fix of the file (see :data:`URBAN3_README_LLH`).

bdsfix runs with Python's bytecode cache (as an installed package: pip compiles the modules
at install); ONE is also timed without it (every module compiled at each start, as under
PYTHONDONTWRITEBYTECODE=1). Each case has one untimed warm-up run of each program.

Each run's CPU time (user + system of the process, from wait4) is printed beside its wall
time, with the ratio of the CPU medians: on a machine shared with other work the wall time
also counts the time a process waited for a core, the CPU time does not.

``--root DIR`` (repeatable) times bdsfix from another source tree too (``python -m service``
run in DIR, e.g. an export of the commit before a change): the trees and rnx2rtkp alternate
(A, B, rnx2rtkp, A, B, ...), so a before/after comparison is made in one sitting.

Run: python bench/bench_vs_rtklib.py [--runs 15] [--files hksc,tst,sim24,one] [--root DIR ...]
(prints figures; no assertions). Needs rnx2rtkp and convbin (Debian package rtklib). The
``-GEC`` rows run both sides with BDS + GPS + Galileo (bdsfix ``--systems C,G,E``,
rnx2rtkp navsys 41).
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.core.geometry import geodetic_to_ecef  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
HKSC = DATA / "hksc-2021"
TST = DATA / "hk-tst-urban-2019"
HKSC_XYZ = np.array([-2414266.9197, 5386768.9868, 2407460.0314])  # header APPROX POSITION

RTKLIB_CONF = """\
pos1-posmode       =single
pos1-frequency     =l1
pos1-soltype       =forward
pos1-elmask        =10
pos1-ionoopt       =brdc
pos1-tropopt       =saas
pos1-sateph        =brdc
pos1-navsys        =32
pos1-posopt5       =on
out-solformat      =xyz
out-outhead        =on
out-timesys        =gpst
out-timeform       =tow
"""
"""rnx2rtkp options: single point, B1I (RTKLIB's frequency 1 of BDS), BDS only (navsys 32),
10 deg, broadcast iono, Saastamoinen, RAIM FDE (posopt5), ECEF output with GPS week/TOW.
A multi-system case sets navsys from its systems (RTKLIB: GPS 1, Galileo 8, BDS 32; L1 C/A
and E1 are frequency 1 of GPS and Galileo)."""
NAVSYS = {"G": 1, "E": 8, "C": 32}
URBAN3 = DATA / "hk-urban-3geo-2020"
URBAN3_README_LLH = (22.3198722, 114.209101778, 3.0)
"""The position ../shared/data/README.md gives as this file's truth. It is not this rover's:
it is the ground truth of AAE6102 Assignment 1's "Urban" IF recording (2019), which the
assignment that ships rover.obs (2020) names only as the skymask's place. Both programs put the
(static) rover about 3.9 km from it and within a metre of each other, so the 3GEO rows use
:func:`rtklib_reference` instead and print the distance to this point."""
LEUVEN = DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf"
STRICT = ("--sigma-cn0-m", "0.3", "--max-exclusions", "1", "--p-fa", "1e-3")
"""bdsfix settings closer to RTKLIB's single point (a weaker C/N0 term, one exclusion, a
1e-3 test): on the urban drive they trade availability for accuracy (docs/method.md,
"Urban drive"); the -strict rows (HKSC-GECs, TST-GECs) run them beside the defaults."""

AIDED = ("--height-aiding", "true", "--screen-predicted-m", "30")
"""bdsfix with height aiding and the prediction screen, the settings for a car
(docs/method.md, "Urban drive"); the -aided rows (HKSC-GECa, TST-GECa) run them beside the
defaults."""

Truth = Callable[[int, float], np.ndarray | None]


@dataclass
class Case:
    name: str
    obs: Path
    nav: Path
    mode: str
    truth: Truth
    epochs: int
    truth_epochs: int = 0  # epochs with a truth: the denominator of availability (0: not shown)
    exclusion: bool = True  # fault exclusion on both sides (bdsfix's default, RTKLIB RAIM FDE)
    systems: str = "C"  # bdsfix --systems; rnx2rtkp navsys from the same letters
    extra_nav: tuple[Path, ...] = ()  # further nav files (TST: the GPS one beside the BDS one)
    # bdsfix's input when it is not the RINEX obs (SBF: `bdsfix replay` of the receiver's own
    # file, its nav blocks the ephemerides; rnx2rtkp reads ``obs``/``nav``, converted by convbin)
    raw: Path | None = None
    bdsfix_flags: tuple[str, ...] = ()  # further bdsfix settings (the -strict rows)


# ---- the simulated day ------------------------------------------------------------------------


def _rinex_float(v: float) -> str:
    return f"{v:19.12E}"


def write_nav(path: Path, ephs: list, iono) -> None:
    """RINEX 3.04 BDS nav (Table A14) of ``ephs``, with GPSA/GPSB ``iono``."""
    from service.core.timebase import BDT_GPS_WEEK_OFFSET, GPS_EPOCH

    def d12(v: float) -> str:
        return f"{v:12.4E}"

    lines = [
        f"{'     3.04           N: GNSS NAV DATA    C: BDS':<60}RINEX VERSION / TYPE",
        f"{'bench_vs_rtklib':<60}PGM / RUN BY / DATE",
        f"{'GPSA ' + ''.join(d12(a) for a in iono.alpha):<60}IONOSPHERIC CORR",
        f"{'GPSB ' + ''.join(d12(b) for b in iono.beta):<60}IONOSPHERIC CORR",
        f"{'    17':<60}LEAP SECONDS",
        f"{'':<60}END OF HEADER",
    ]
    bdt0 = GPS_EPOCH + dt.timedelta(weeks=BDT_GPS_WEEK_OFFSET)
    for e in sorted(ephs, key=lambda e: (e.prn, e.toe_sow_s)):
        toc = bdt0 + dt.timedelta(weeks=e.week, seconds=e.toc_sow_s)
        orbit = (
            (e.aode, e.crs_m, e.delta_n_rad_s, e.m0_rad),
            (e.cuc_rad, e.e, e.cus_rad, e.sqrt_a_sqrt_m),
            (e.toe_sow_s, e.cic_rad, e.omega0_rad, e.cis_rad),
            (e.i0_rad, e.crc_m, e.omega_rad, e.omega_dot_rad_s),
            (e.idot_rad_s, 0.0, e.week, 0.0),
            (2.0, 0, 0.0, 0.0),
            (e.toe_sow_s - 60.0, 0),
        )
        lines.append(
            f"{e.prn} {toc:%Y %m %d %H %M %S}"
            + "".join(_rinex_float(v) for v in (e.af0_s, e.af1_s_s, e.af2_s_s2))
        )
        lines += ["    " + "".join(_rinex_float(float(v)) for v in row) for row in orbit]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")


def make_sim_day(workdir: Path, hours: float = 24.0, step_s: float = 30.0) -> Case:
    """A simulated reference-station day: nav + obs files and the true position."""
    from drivers.rinex import read_nav
    from service.core.ephemeris import EphemerisStore
    from service.core.timebase import datetime_from_gpst, gpst_to_bdt, normalize
    from service.core.types import KlobucharParams
    from service.sim.keplerian import table1_ephemerides
    from service.sim.rangegen import true_ranges

    iono = KlobucharParams(
        (0.5588e-08, 0.1490e-07, -0.5961e-07, -0.1192e-06),
        (0.8397e05, 0.9830e05, -0.6554e05, -0.5243e06),
        "GPS",
    )
    ephs = [e for h in range(-1, math.ceil(hours) + 2) for e in table1_ephemerides(h * 3600.0)]
    nav_path = workdir / "sim24.nav"
    write_nav(nav_path, ephs, iono)
    store = EphemerisStore(max_age_s=7200.0)
    for sets in read_nav(nav_path).ephemerides.values():
        store.add_all(sets)
    week0, tow0 = normalize(*_first_toe_gpst(ephs))
    rng = np.random.default_rng(14)
    out = [
        f"{'     3.04           OBSERVATION DATA    C: BDS':<60}RINEX VERSION / TYPE",
        f"{'bench_vs_rtklib':<60}PGM / RUN BY / DATE",
        f"{'SIM24':<60}MARKER NAME",
        f"{'        0.0000        0.0000        0.0000':<60}APPROX POSITION XYZ",
        f"{'        0.0000        0.0000        0.0000':<60}ANTENNA: DELTA H/E/N",
        f"{'C    2 C2I S2I':<60}SYS / # / OBS TYPES",
        f"{step_s:10.3f}{'':<50}INTERVAL",
    ]
    first = datetime_from_gpst(week0, tow0)
    out.append(f"{first:  %Y    %m    %d    %H    %M   %S}.0000000     GPS{'':<9}TIME OF FIRST OBS")
    out.append(f"{'':<60}END OF HEADER")
    prns = sorted({e.prn for e in ephs})
    n_epochs = int(hours * 3600 / step_s)
    clock_s = 2.5e-4
    for k in range(n_epochs):
        week, tow = normalize(week0, tow0 + k * step_s)
        bdt = gpst_to_bdt(week, tow)
        sel = [e for p in prns if (e := store.select(p, *bdt)) is not None]
        # a steered reference receiver: the time tag (true time + clock offset) is on the
        # 30 s grid, so the signal arrived at grid time - clock offset
        r = true_ranges(
            store.arrays(sel),
            HKSC_XYZ,
            week,
            tow - clock_s,
            clock_s,
            iono=iono,
            tropo=True,
            noise_m=0.5,
            rng=rng,
        )
        use = np.flatnonzero(r.el_rad > math.radians(5.0))
        when = datetime_from_gpst(week, tow)
        out.append(f"> {when:%Y %m %d %H %M %S}.0000000  0{len(use):3d}")
        for i in use:
            pr = r.pr_m[i]
            cn0 = 35.0 + 15.0 * math.sin(float(r.el_rad[i]))
            out.append(f"{r.prn[i]}{pr:14.3f}  {cn0:14.3f}  ")
    obs_path = workdir / "sim24.obs"
    obs_path.write_text("\n".join(out) + "\n", encoding="ascii")
    return Case("SIM24", obs_path, nav_path, "both", lambda w, t: HKSC_XYZ, n_epochs)


def _first_toe_gpst(ephs: list) -> tuple[int, float]:
    from service.core.timebase import bdt_to_gpst

    e = min(ephs, key=lambda e: (e.week, e.toe_sow_s))
    return bdt_to_gpst(e.week, e.toe_sow_s + 3600.0)  # one hour after the first sets


# ---- the real files ---------------------------------------------------------------------------


def tst_truth() -> Truth:
    """(GPS week, whole TOW) -> ECEF truth, from groundTruth_TST.csv (week, TOW, lat, lon, h)."""
    table: dict[tuple[int, int], np.ndarray] = {}
    with open(TST / "groundTruth_TST.csv", encoding="ascii") as f:
        for row in csv.reader(f):
            try:
                week, tow, lat, lon, h = (float(v) for v in row[:5])
            except ValueError:
                continue
            table[(int(week), round(tow))] = geodetic_to_ecef(
                math.radians(lat), math.radians(lon), h
            )
    return lambda w, t: table.get((w, round(t)))


def one_epoch(workdir: Path) -> Path:
    """HKSC's header and first epoch as a file of its own."""
    out, n = [], 0
    with open(HKSC / "hksc1610.obs", encoding="ascii") as f:
        in_header = True
        for line in f:
            if not in_header and line.startswith(">"):
                n += 1
                if n == 2:
                    break
            out.append(line)
            in_header = in_header and "END OF HEADER" not in line
    path = workdir / "one.obs"
    path.write_text("".join(out), encoding="ascii")
    return path


def sbf_case(workdir: Path) -> Case:
    """The Leuven Septentrio capture: bdsfix replays the SBF file itself; rnx2rtkp reads
    RINEX 3.04 obs and nav converted from it by RTKLIB's convbin (``-r sbf``). Truth per
    epoch: the receiver's own PVTGeodetic (SBAS-aided, metre level)."""
    from pysbf2 import SBFReader

    obs, nav = workdir / "leuven.obs", workdir / "leuven.nav"
    cmd = ["convbin", "-r", "sbf", "-v", "3.04", "-od", "-os", "-o", str(obs), "-n", str(nav)]
    subprocess.run([*cmd, str(LEUVEN)], check=True, capture_output=True)
    table: dict[int, np.ndarray] = {}
    with open(LEUVEN, "rb") as fh:
        for raw, msg in SBFReader(fh):
            if msg.identity == "PVTGeodetic":
                tow = round(int.from_bytes(raw[8:12], "little") / 1000)
                table[tow] = geodetic_to_ecef(msg.Latitude, msg.Longitude, msg.Height)
    truth: Truth = lambda w, t: table.get(round(t))  # noqa: E731
    n = len(table)
    return Case("SBF-GEC", obs, nav, "spp", truth, n, truth_epochs=n, systems="C,G,E", raw=LEUVEN)


# ---- running and scoring ----------------------------------------------------------------------


def _bdsfix_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("bdsfix")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "service"]


def run_timed(
    cmd: list[str], env: dict[str, str] | None = None, cwd: Path | None = None
) -> tuple[float, float]:
    """Wall time and CPU time (user + system, of the process and its children) [s]."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=cwd
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return wall, usage.ru_utime + usage.ru_stime


def bdsfix_env(workdir: Path, bytecode: bool) -> dict[str, str]:
    """bdsfix's environment: with ``bytecode``, Python's compiled-module cache on (in the
    work directory), as an installed package has it (pip compiles at install); without,
    every module is compiled from source at each start (PYTHONDONTWRITEBYTECODE=1)."""
    env = dict(os.environ)
    if bytecode:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(workdir / "pycache")
    else:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def rtklib_conf(systems: str, exclusion: bool = True) -> str:
    """:data:`RTKLIB_CONF` for ``systems`` (navsys), without RAIM FDE unless ``exclusion``."""
    text = RTKLIB_CONF
    if not exclusion:
        text = text.replace("pos1-posopt5       =on\n", "")
    navsys = sum(NAVSYS[s] for s in systems.split(","))
    return text.replace("pos1-navsys        =32", f"pos1-navsys        ={navsys}")


def rtklib_reference(obs: Path, nav: Path, systems: str, workdir: Path) -> np.ndarray:
    """The median of rnx2rtkp's single-point fixes of a static receiver's file: a reference
    for a file without a truth of its own, from the independent program (so it favours
    rnx2rtkp's RMS: a bdsfix RMS at or below rnx2rtkp's about it is a conservative result)."""
    conf = workdir / "reference.conf"
    conf.write_text(rtklib_conf(systems), encoding="ascii")
    out = workdir / "reference.pos"
    cmd = ["rnx2rtkp", "-x", "0", "-k", str(conf), "-o", str(out), str(obs), str(nav)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rows = [
        [float(v) for v in line.split()[2:5]]
        for line in out.read_text().splitlines()
        if line.strip() and not line.startswith("%")
    ]
    return np.median(np.array(rows), axis=0)


def rms(errors: list[float]) -> float:
    return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.nan


def score_bdsfix(
    path: Path, truth: Truth, by_mode: bool = False
) -> dict[str, dict[tuple[int, int], float]]:
    """Per solver: (week, round(tow)) -> 3D error of each fix."""
    out: dict[str, dict[tuple[int, int], float]] = {"fast": {}, "spp": {}}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r.get("class", "FIX") != "FIX":
            continue
        if r.get("mode") in ("fast", "spp") and "x_ecef_m" in r:
            t = truth(r["gpst_week"], r["gpst_tow_s"])
            if t is not None:
                key = (r["gpst_week"], round(r["gpst_tow_s"]))
                # a replay's FIX records name the pipeline ("solver": "fast") and the solution
                # ("mode": "spp" when the epoch's ranges were full): scored by the solution
                err = float(np.linalg.norm(np.subtract(r["x_ecef_m"], t)))
                out[r["mode"] if by_mode else r["solver"]][key] = err
    return out


def _pcts(errors: list[float]) -> str:
    if not errors:
        return "-"
    p50, p95 = np.percentile(errors, [50, 95])
    return f"{p50:.1f}/{p95:.1f}/{max(errors):.1f} m"


def score_rtklib(path: Path, truth: Truth) -> dict[tuple[int, int], float]:
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split()
        week, tow, x = int(f[0]), float(f[1]), np.array([float(v) for v in f[2:5]])
        t = truth(week, tow)
        if t is not None:
            out[(week, round(tow))] = float(np.linalg.norm(x - t))
    return out


def bench_case(
    case: Case,
    runs: int,
    workdir: Path,
    conf: Path,
    env: dict[str, str],
    label: str = "",
    roots: list[Path] | None = None,
) -> None:
    """Time ``case`` on both sides (with ``roots``: bdsfix from each source tree, in turn)."""
    bds_out, rtk_out = workdir / f"{case.name}.jsonl", workdir / f"{case.name}.pos"
    navs = [str(case.nav), *map(str, case.extra_nav)]
    if case.raw is None:
        args = ["solve", str(case.obs), *navs, "--mode", case.mode, "--systems", case.systems]
        args += list(case.bdsfix_flags)
        out_flag = "--out"
    else:
        args = ["replay", str(case.raw), "--max-speed", "--nmea-out", os.devnull]
        args += ["--systems", case.systems]
        out_flag = "--jsonl-out"
    if not case.exclusion:
        args += ["--max-exclusions", "0"]
    text = rtklib_conf(case.systems, case.exclusion)
    if text != RTKLIB_CONF:
        conf = conf.with_name(f"{case.name}.conf")
        conf.write_text(text, encoding="ascii")
    rtk = ["rnx2rtkp", "-x", "0", "-k", str(conf), "-o", str(rtk_out), str(case.obs), *navs]
    # (name, command, working directory) of each bdsfix tree
    outs = [bds_out]
    trees: list[tuple[str, list[str], Path | None]] = [
        ("", [*_bdsfix_cmd(), *args, out_flag, str(bds_out)], None)
    ]
    if roots:  # each tree writes its own output; the last tree's is scored
        outs = [bds_out.with_suffix(f".{k}.jsonl") for k in range(len(roots))]
        trees = [
            (str(r), [sys.executable, "-m", "service", *args, out_flag, str(out)], r)
            for r, out in zip(roots, outs, strict=True)
        ]
    for _, cmd, cwd in trees:  # warm-up (file cache, bytecode cache), not timed
        try:
            run_timed(cmd, env, cwd)
        except subprocess.CalledProcessError as exc:  # e.g. SBF-RNX: convbin wrote no BDS nav
            print(f"{case.name + label:<8} bdsfix exits {exc.returncode} on this input: not timed")
            return
    run_timed(rtk)
    t_bds: list[list[tuple[float, float]]] = [[] for _ in trees]
    t_rtk: list[tuple[float, float]] = []
    for _ in range(runs):
        for k, (_, cmd, cwd) in enumerate(trees):
            t_bds[k].append(run_timed(cmd, env, cwd))
        t_rtk.append(run_timed(rtk))
    mr = statistics.median(w for w, _ in t_rtk)
    cr = statistics.median(c for _, c in t_rtk)
    how = "replay (SBF)" if case.raw is not None else f"solve --mode {case.mode}"
    for (tree, _, _), times in zip(trees, t_bds, strict=True):
        mb = statistics.median(w for w, _ in times)
        cb = statistics.median(c for _, c in times)
        print(
            f"{case.name + label:<8} {case.epochs:5d} epochs  bdsfix {how:<17} "
            f"{mb:7.3f} s (min {min(w for w, _ in times):.3f})  rnx2rtkp {mr:6.3f} s "
            f"(min {min(w for w, _ in t_rtk):.3f})  ratio {mb / mr:5.1f}x   ({runs} "
            f"alternating runs, medians); CPU {cb:6.3f} s vs {cr:6.3f} s, ratio {cb / cr:4.1f}x"
            + (f"  [{tree}]" if tree else "")
        )
    if len(outs) > 1:
        same = all(o.read_bytes() == outs[0].read_bytes() for o in outs[1:])
        print(f"       outputs of the {len(outs)} trees byte-identical: {same}")
    if case.name == "ONE":
        return
    sb = score_bdsfix(outs[-1], case.truth, by_mode=case.raw is not None)
    sr = score_rtklib(rtk_out, case.truth)
    for solver in ("spp", "fast") if case.mode == "both" else (case.mode,):
        mine = sb[solver]
        common = sorted(set(mine) & set(sr))
        print(
            f"       3D RMS vs truth: bdsfix {solver:<4} {rms(list(mine.values())):7.2f} m over "
            f"{len(mine)} fixes; rnx2rtkp {rms(list(sr.values())):7.2f} m over {len(sr)}; "
            f"on the {len(common)} epochs both fixed: bdsfix "
            f"{rms([mine[k] for k in common]):.2f} m, rnx2rtkp {rms([sr[k] for k in common]):.2f} m"
        )
        if case.truth_epochs:  # availability: fixes over the epochs that have a truth
            print(
                f"       availability of {case.truth_epochs} truth epochs: bdsfix {solver:<4} "
                f"{100 * len(mine) / case.truth_epochs:5.1f} %, rnx2rtkp "
                f"{100 * len(sr) / case.truth_epochs:5.1f} %; 3D error p50/p95/max: bdsfix "
                f"{_pcts(list(mine.values()))}, rnx2rtkp {_pcts(list(sr.values()))}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=15, help="alternating runs per file")
    ap.add_argument(
        "--files",
        default="one,hksc,tst,sim24,hksc-gec,tst-gec,3geo,3geo-gec,sbf-gec",
        help="which files, comma-separated (-gec: BDS + GPS + Galileo on both sides)",
    )
    ap.add_argument("--sim-hours", type=float, default=24.0, help="length of the simulated day")
    ap.add_argument(
        "--root",
        type=Path,
        action="append",
        help="source tree to run bdsfix from (python -m service in it; repeatable, runs "
        "alternate); default: the installed bdsfix",
    )
    args = ap.parse_args()
    if shutil.which("rnx2rtkp") is None:
        sys.exit("bench_vs_rtklib: rnx2rtkp not found (sudo apt-get install rtklib)")
    want = args.files.split(",")
    with tempfile.TemporaryDirectory(prefix="bench_vs_rtklib.") as tmp:
        workdir = Path(tmp)
        conf = workdir / "bds-spp.conf"
        conf.write_text(RTKLIB_CONF, encoding="ascii")
        cases = []
        if "one" in want:
            cases.append(Case("ONE", one_epoch(workdir), HKSC / "hksc1610.nav", "spp", None, 1))  # type: ignore[arg-type]
        if "hksc" in want:
            cases.append(
                Case(
                    "HKSC",
                    HKSC / "hksc1610.obs",
                    HKSC / "hksc1610.nav",
                    "spp",
                    lambda w, t: HKSC_XYZ,
                    205,
                    205,
                )
            )
        if "tst" in want:
            cases.append(
                Case(
                    "TST",
                    TST / "COM3_190428_124409.obs",
                    TST / "hksc1180.19b",
                    "spp",
                    tst_truth(),
                    1760,
                    485,
                )
            )
            cases.append(replace(cases[-1], name="TST-0", exclusion=False))
        if "hksc-gec" in want:
            cases.append(
                Case(
                    "HKSC-GEC",
                    HKSC / "hksc1610.obs",
                    HKSC / "hksc1610.nav",
                    "spp",
                    lambda w, t: HKSC_XYZ,
                    205,
                    205,
                    systems="C,G,E",
                )
            )
        if "tst-gec" in want:  # the drive has no Galileo nav file: its E rows go unused
            cases.append(
                Case(
                    "TST-GEC",
                    TST / "COM3_190428_124409.obs",
                    TST / "hksc1180.19b",
                    "spp",
                    tst_truth(),
                    1760,
                    485,
                    systems="C,G,E",
                    extra_nav=(TST / "hksc1180.19n",),
                )
            )
        for name in ("hksc-gec", "tst-gec"):  # the same with RTKLIB-like strictness
            if f"{name}-strict" in want:
                base = next(c for c in cases if c.name == name.upper())
                cases.append(replace(base, name=f"{base.name}s", bdsfix_flags=STRICT))
            if f"{name}-aided" in want:  # height aiding (a car's settings)
                base = next(c for c in cases if c.name == name.upper())
                cases.append(replace(base, name=f"{base.name}a", bdsfix_flags=AIDED))
        if "3geo" in want or "3geo-gec" in want:
            xyz = rtklib_reference(
                URBAN3 / "rover.obs", URBAN3 / "navigation_message.nav", "C,G,E", workdir
            )
            llh = URBAN3_README_LLH
            stated = geodetic_to_ecef(math.radians(llh[0]), math.radians(llh[1]), llh[2])
            print(
                f"3GEO reference: rnx2rtkp's median C,G,E fix {np.round(xyz, 1).tolist()} m "
                f"(the data README's position is {np.linalg.norm(xyz - stated):.0f} m from it "
                "and belongs to another recording); its RMS about its own median flatters it"
            )
            urban3 = Case(
                "3GEO",
                URBAN3 / "rover.obs",
                URBAN3 / "navigation_message.nav",
                "spp",
                lambda w, t: xyz,
                300,
                300,
            )
            if "3geo" in want:
                cases.append(urban3)
            if "3geo-gec" in want:
                cases.append(replace(urban3, name="3GEO-GEC", systems="C,G,E"))
        if "sbf-gec" in want:
            cases.append(sbf_case(workdir))
            # bdsfix on convbin's RINEX as well: the very input rnx2rtkp reads
            cases.append(replace(cases[-1], name="SBF-RNX", raw=None))
        if "sim24" in want:
            t0 = time.perf_counter()
            cases.append(make_sim_day(workdir, args.sim_hours))
            # the SPP-only bound on every file of >= 900 epochs applies to this one too
            cases.append(replace(cases[-1], name="SIM24s", mode="spp"))
            print(f"(simulated day written in {time.perf_counter() - t0:.1f} s)")
        print(
            f"bench_vs_rtklib: {' '.join(_bdsfix_cmd())} vs rnx2rtkp, {args.runs} runs each; "
            f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the start"
        )
        env = bdsfix_env(workdir, bytecode=True)
        roots = [r.resolve() for r in args.root] if args.root else None
        for case in cases:
            bench_case(case, args.runs, workdir, conf, env, roots=roots)
        if "one" in want:  # start-up when every module is compiled at each start
            no_cache = bdsfix_env(workdir, False)
            bench_case(cases[0], args.runs, workdir, conf, no_cache, "*", roots=roots)
            print("       (ONE*: no bytecode cache, PYTHONDONTWRITEBYTECODE=1)")
        print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
