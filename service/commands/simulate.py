"""``bdsfix simulate``: the virtual receiver's UBX stream to a file, stdout or a pty.

Ephemerides come from a RINEX nav file (``--nav``) or the built-in Table 1 set; the start
time defaults to the nav file's first BDS toe (or Table 1's epoch). ``--pty`` creates a
pseudo-terminal pair, prints the device path to stderr and writes to it, paced in real time
unless ``--max-speed``. ``--pty --wait-config`` makes it a configurable u-blox receiver that
answers CFG messages and starts silent (:mod:`service.sim.configurable`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

from service.commands.options import check_range, full_rule, parse_start
from service.core.errors import ConfigError, InputError
from service.core.files import open_output
from service.core.timebase import gpst_from_utc, normalize
from service.core.types import Ephemeris, KlobucharParams
from service.sim.rtcm import broadcast_sets, frame_1042
from service.sim.scenario import broadcast_table1, default_start_gpst
from service.sim.simulator import SimConfig, Simulator


def _ephemerides(nav: str | None) -> tuple[list[Ephemeris], KlobucharParams | None]:
    if nav is None:
        return broadcast_table1(), None
    from drivers.rinex import read_nav
    from service.core.ephemeris import ephemeris_problem

    data = read_nav(nav)
    ephs = [e for items in data.ephemerides.values() for e in items if ephemeris_problem(e) is None]
    if not ephs:
        raise InputError(f"{nav}: no healthy BDS ephemeris that passes the entry checks")
    return ephs, data.iono_bds


def _serve_configurable(
    args: argparse.Namespace,
    ephs: list[Ephemeris],
    cfg: SimConfig,
    iono: KlobucharParams | None,
) -> int:
    """``--pty --wait-config``: a receiver that answers CFG messages and sends only what it
    was asked for (:mod:`service.sim.configurable`)."""
    import tty

    from service.sim.cfg import CfgResponder
    from service.sim.configurable import ConfigurableReceiver

    if not args.pty:
        raise ConfigError("--wait-config needs --pty (the host must be able to write to it)")
    base_ms = 1000.0 / cfg.rate_hz
    if abs(base_ms - round(base_ms)) > 1e-9:
        raise ConfigError(
            f"--wait-config needs a whole-millisecond period, got --rate-hz {cfg.rate_hz:g}"
        )
    try:
        responder = CfgResponder(
            port=args.port, base_period_ms=round(base_ms), nak=args.nak or (), silent=args.no_answer
        )
    except ValueError as exc:
        raise ConfigError(f"--nak: {exc}") from exc

    def make_sim(offset_s: float) -> Simulator:
        week, tow = normalize(cfg.start_gpst_week, cfg.start_gpst_tow_s + offset_s)
        return Simulator(ephs, replace(cfg, start_gpst_week=week, start_gpst_tow_s=tow), iono)

    master, slave = os.openpty()
    tty.setraw(slave)
    print(os.ttyname(slave), file=sys.stderr, flush=True)
    try:
        stats = ConfigurableReceiver(
            master, make_sim, responder, base_period_ms=round(base_ms)
        ).serve()
    finally:
        time.sleep(0.5)
        os.close(master)
        os.close(slave)
    sent = ", ".join(sorted(responder.outputs)) or "no output"
    print(
        f"bdsfix simulate: {stats.epochs_sent} epochs sent ({sent}), "
        f"{stats.answered} CFG messages answered, {stats.restarts} restarts, "
        f"{stats.dropped_bytes} bytes lost while nobody read",
        file=sys.stderr,
    )
    return 0


def main_simulate(args: argparse.Namespace) -> int:
    for flag, value in (("--rate-hz", args.rate_hz), ("--duration-s", args.duration_s)):
        if not (value > 0 and value < float("inf")):
            raise ConfigError(f"{flag} must be a positive number, got {value}")
    check_range("--lat-deg", args.lat_deg, -90.0, 90.0)
    check_range("--lon-deg", args.lon_deg, -180.0, 360.0)
    check_range("--alt-m", args.alt_m, -1000.0, 1_100_000.0)
    ephs, iono = _ephemerides(args.nav)
    if args.start:
        week, tow = gpst_from_utc(parse_start(args.start))
    else:
        week, tow = default_start_gpst(ephs if args.nav else None)
    cfg = SimConfig(
        lat_deg=args.lat_deg,
        lon_deg=args.lon_deg,
        alt_m=args.alt_m,
        start_gpst_week=week,
        start_gpst_tow_s=tow,
        duration_s=args.duration_s,
        rate_hz=args.rate_hz,
        clock_offset_s=args.clock_offset_s,
        noise_m=args.noise_m,
        seed=args.seed,
        full_rule=full_rule(args),
    )
    sim = Simulator(ephs, cfg, iono)
    if not sim.prns:
        raise ConfigError("no satellite in view at that place and time")
    if args.wait_config:
        return _serve_configurable(args, ephs, cfg, iono)
    if args.nak or args.no_answer:
        raise ConfigError("--nak and --no-answer need --pty --wait-config")
    master = slave = None
    if args.pty:
        master, slave = os.openpty()
        print(os.ttyname(slave), file=sys.stderr, flush=True)
        write = lambda b: os.write(master, b)  # noqa: E731
    elif args.out in (None, "-"):
        write = sys.stdout.buffer.write
    else:
        fh = open_output(args.out, binary=True)  # InputError: unwritable or a symlink
        write = fh.write
    t0 = time.monotonic()
    try:
        if args.ephemerides:  # what the stream was made with, as an assisted receiver has it
            write(b"".join(frame_1042(e) for e in broadcast_sets(ephs, sim.prns, week, tow)))
        for ep, data in sim.ubx_epochs():
            if not args.max_speed and (args.pty or args.realtime):
                delay = t0 + ep.t_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            write(data)
    finally:
        if master is not None and slave is not None:
            time.sleep(0.5)
            os.close(master)
            os.close(slave)
        elif args.out not in (None, "-"):
            fh.close()
        else:
            sys.stdout.buffer.flush()
    print(
        f"bdsfix simulate: {len(sim.prns)} satellites ({', '.join(sim.prns)}), "
        f"{round(cfg.duration_s * cfg.rate_hz)} epochs",
        file=sys.stderr,
    )
    return 0
