"""``bdsfix simulate``: the virtual receiver's UBX stream to a file, stdout or a pty.

Ephemerides come from a RINEX nav file (``--nav``) or the built-in Table 1 set; the start
time defaults to the nav file's first BDS toe (or Table 1's epoch). ``--pty --wait-config``
makes it a configurable u-blox receiver that answers CFG messages and starts silent
(:mod:`service.sim.configurable`).

``--pty`` creates a pseudo-terminal pair (raw), prints the device path to stderr (and links
``--link PATH`` to it), and waits for a reader: the scenario starts when a program opens
the device (the master stops reporting POLLHUP), so nothing is written to nobody. The
stream is paced in real time unless ``--max-speed``. The RTCM 1042 ephemerides go out at
the start and again every ``--ephemerides-every-s`` (1 s by default on a pty), as a real
receiver repeats its navigation data: a reader that flushes its input on open (pyserial
does) or comes late still gets them within a second (issue 23: without the repeat the
first fast fix of ``bdsfix run`` came 44 s late). The writes never block the scenario:
when the reader leaves (POLLHUP again), what is written is dropped and counted, and the
command ends at ``--duration-s`` all the same; with ``--max-speed`` the pty's flow control
paces the stream while a reader is there.
"""

from __future__ import annotations

import argparse
import os
import select
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from service.commands.options import check_range, full_rule, parse_start, systems_of
from service.core.errors import ConfigError, InputError
from service.core.files import open_output
from service.core.systems import GnssSystem, parse_systems, system_of
from service.core.timebase import gpst_from_utc, normalize
from service.core.types import Ephemeris, KlobucharParams
from service.sim.rtcm import broadcast_sets, frame_1042
from service.sim.scenario import broadcast_table1, default_start_gpst
from service.sim.simulator import SimConfig, Simulator

if TYPE_CHECKING:
    from service.output.publish import Publishers


def _ephemerides(
    nav: str | None, systems: frozenset[str] = frozenset("C")
) -> tuple[list[Ephemeris], KlobucharParams | None, KlobucharParams | None]:
    """The ephemerides to simulate, the BDS Klobuchar set and, with other systems, the GPS one
    (their rows' delay)."""
    if nav is None:
        return broadcast_table1(), None, None
    from drivers.rinex import read_nav
    from service.core.ephemeris import ephemeris_problem

    data = read_nav(nav, systems)
    iono_gps = data.iono_gps if systems != frozenset("C") else None
    ephs = [e for items in data.ephemerides.values() for e in items if ephemeris_problem(e) is None]
    if not any(system_of(e.prn) is GnssSystem.BDS for e in ephs):  # a BeiDou receiver first
        raise InputError(f"{nav}: no healthy BDS ephemeris that passes the entry checks")
    return ephs, data.iono_bds, iono_gps


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
    device = os.ttyname(slave)
    try:
        _link(device, args.link)
        print(device, file=sys.stderr, flush=True)
        stats = ConfigurableReceiver(
            master, make_sim, responder, base_period_ms=round(base_ms)
        ).serve()
    finally:
        time.sleep(0.5)
        os.close(master)
        os.close(slave)
        _unlink(device, args.link)
    sent = ", ".join(sorted(responder.outputs)) or "no output"
    print(
        f"bdsfix simulate: {stats.epochs_sent} epochs sent ({sent}), "
        f"{stats.answered} CFG messages answered, {stats.restarts} restarts, "
        f"{stats.dropped_bytes} bytes lost while nobody read",
        file=sys.stderr,
    )
    return 0


def _open_outputs(asked: list[str]) -> Publishers:
    """``--output KIND:SPEC``: the outputs of the stream solved here (opened before the
    stream starts: one that cannot open is the command's error)."""
    from service.commands.run import build_publishers
    from service.output.sinks import OutputSpec

    return build_publishers([OutputSpec.parse(text) for text in asked])


def _solve_here(chunks: Iterator[bytes], gps_week: int, outputs: Publishers) -> None:
    """Decode the bytes written and solve them as ``bdsfix replay`` of the same stream does
    (the stream's own RTCM 1042 sets or subframes give the ephemerides), publishing to
    ``outputs``; the summary of that solution on stderr."""
    from service.commands.run import decode_chunks
    from service.commands.summary import stream_lines
    from service.core.ephemeris import EphemerisStore
    from service.daemon.loop import Runner
    from service.engine.pipeline import Pipeline

    runner = Runner(
        decode_chunks(chunks, gps_week), Pipeline(EphemerisStore()), outputs, inline=True
    )
    n = runner.run()
    for line in stream_lines("simulate", n, runner.counters(), runner.skipped()):
        print(line, file=sys.stderr)


PTY_POLL_S = 0.05
"""How often the pty is looked at while it waits for a reader or for room [s]."""


@dataclass
class PtyWriter:
    """The master side of a pty whose slave is closed here: the reader is whoever opens
    the device. Writes are non-blocking; bytes that find no reader (or, unless ``wait``,
    a full buffer) are dropped and counted, as a UART drops them."""

    fd: int
    wait: bool = False
    """Wait for room while a reader is there (``--max-speed``: its flow control paces)."""
    written: int = 0
    dropped: int = 0

    def __post_init__(self) -> None:
        os.set_blocking(self.fd, False)
        self._poll = select.poll()
        self._poll.register(self.fd, select.POLLOUT)

    def reader_present(self) -> bool:
        """Whether a program has the slave open (the master reports no POLLHUP)."""
        return not any(ev & select.POLLHUP for _, ev in self._poll.poll(0))

    def wait_for_reader(self) -> None:
        while not self.reader_present():
            time.sleep(PTY_POLL_S)

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if not self.reader_present():
                self.dropped += len(view)
                return
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                if not self.wait:
                    self.dropped += len(view)
                    return
                self._poll.poll(round(PTY_POLL_S * 1000))
                continue
            self.written += n
            view = view[n:]


def _link(device: str, link: str | None) -> None:
    """Point the symlink ``link`` at ``device`` (an old symlink there is replaced, anything
    else refused: InputError)."""
    if not link:
        return
    if os.path.lexists(link) and not os.path.islink(link):
        raise InputError(f"--link {link}: exists and is not a symlink")
    tmp = f"{link}.new"
    try:
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(device, tmp)
        os.replace(tmp, link)
    except OSError as exc:
        raise InputError(f"--link {link}: {exc.strerror}") from exc


def _unlink(device: str, link: str | None) -> None:
    """Remove ``link`` if it still points at ``device``."""
    try:
        if link and os.readlink(link) == device:
            os.unlink(link)
    except OSError:
        pass


def _open_pty(link: str | None) -> tuple[int, str]:
    """A raw pty pair whose slave is closed again (the master reports POLLHUP until a
    reader opens it); its master and device path, linked from ``link`` if given."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)  # binary from the first byte, before the reader configures the port
    device = os.ttyname(slave)
    os.close(slave)
    try:
        _link(device, link)
    except InputError:
        os.close(master)
        raise
    return master, device


def main_simulate(args: argparse.Namespace) -> int:
    for flag, value in (("--rate-hz", args.rate_hz), ("--duration-s", args.duration_s)):
        if not (value > 0 and value < float("inf")):
            raise ConfigError(f"{flag} must be a positive number, got {value}")
    check_range("--lat-deg", args.lat_deg, -90.0, 90.0)
    check_range("--lon-deg", args.lon_deg, -180.0, 360.0)
    check_range("--alt-m", args.alt_m, -1000.0, 1_100_000.0)
    systems = systems_of(args)
    measx = parse_systems(args.measx_systems)
    if not measx <= systems:
        raise ConfigError(
            f"--measx-systems {args.measx_systems!r}: {','.join(sorted(measx - systems))} "
            f"not simulated (--systems {','.join(sorted(systems))})"
        )
    ephs, iono, iono_gps = _ephemerides(args.nav, systems)
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
        systems="".join(sorted(systems)),
        measx_systems="".join(sorted(measx)),
    )
    sim = Simulator(ephs, cfg, iono, iono_gps)
    if not sim.prns:
        raise ConfigError("no satellite in view at that place and time")
    if args.wait_config:
        if args.output:
            raise ConfigError("--output is not with --wait-config (the host solves that stream)")
        return _serve_configurable(args, ephs, cfg, iono)
    if args.nak or args.no_answer:
        raise ConfigError("--nak and --no-answer need --pty --wait-config")
    if args.link and not args.pty:
        raise ConfigError("--link needs --pty")
    every_s = args.ephemerides_every_s
    if every_s is None:
        every_s = 1.0 if args.pty else 0.0
    if not (every_s >= 0 and every_s < float("inf")):
        raise ConfigError(f"--ephemerides-every-s must be 0 or a positive number, got {every_s}")
    outputs = _open_outputs(args.output) if args.output else None
    master = None
    pty: PtyWriter | None = None
    write: Callable[[bytes], object]
    if args.pty:
        master, device = _open_pty(args.link)
        print(device, file=sys.stderr, flush=True)
        pty = PtyWriter(master, wait=args.max_speed)
        write = pty.write
    elif args.out in (None, "-"):
        write = sys.stdout.buffer.write
    else:
        fh = open_output(args.out, binary=True)  # InputError: unwritable or a symlink
        write = fh.write
    # RTCM 1042 carries BeiDou sets; GPS and Galileo ones reach a replay in the SFRBX
    bds = [p for p in sim.prns if p[0] == "C"]
    sets = b"".join(frame_1042(e) for e in broadcast_sets(ephs, bds, week, tow))

    def stream() -> Iterator[bytes]:
        """Write the scenario (paced as asked); each chunk written, for ``--output``."""
        if pty is not None:
            print("bdsfix simulate: waiting for a reader of the pty", file=sys.stderr, flush=True)
            pty.wait_for_reader()
        t0 = time.monotonic()
        next_sets_s = 0.0
        for ep, data in sim.ubx_epochs():
            if not args.max_speed and (args.pty or args.realtime):
                delay = t0 + ep.t_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if args.ephemerides and ep.t_s >= next_sets_s:
                # what the stream was made with, as an assisted receiver has it, repeated
                write(sets)
                yield sets
                next_sets_s = ep.t_s + every_s if every_s > 0 else float("inf")
            write(data)
            yield data

    try:
        if outputs is None:
            for _chunk in stream():
                pass
        else:
            _solve_here(stream(), week, outputs)
    finally:
        if outputs is not None:
            outputs.close()
        if master is not None:
            time.sleep(0.5)  # the reader takes what is in the pty before it hangs up
            os.close(master)
            _unlink(device, args.link)
        elif args.out not in (None, "-"):
            fh.close()
        else:
            sys.stdout.buffer.flush()
    lost = f", {pty.dropped} bytes lost while nobody read" if pty is not None else ""
    print(
        f"bdsfix simulate: {len(sim.prns)} satellites ({', '.join(sim.prns)}), "
        f"{round(cfg.duration_s * cfg.rate_hz)} epochs{lost}",
        file=sys.stderr,
    )
    return 0
