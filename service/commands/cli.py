"""The ``bdsfix`` command line (contract in docs/architecture.md): the parser and the
dispatch to one module per subcommand; only this entry point configures logging."""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import sys
import traceback
from collections.abc import Callable, Sequence
from typing import NoReturn

from service import __version__
from service.core.errors import EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, BdsfixError

log = logging.getLogger(__name__)

# subcommand -> "module:function"; the function takes the parsed namespace, returns an exit code
_HANDLERS: dict[str, str] = {
    "solve": "service.commands.solve:main_solve",
    "coverage": "service.commands.coverage:main_coverage",
    "replay": "service.commands.run:main_replay",
    "run": "service.commands.run:main_run",
    "sub": "service.commands.run:main_sub",
    "simulate": "service.commands.simulate:main_simulate",
    "ttff": "service.commands.ttff:main_ttff",
    "configure": "service.commands.configure:main_configure",
}


def _float_list(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from exc


def _terminal_columns() -> int:
    """``shutil.get_terminal_size().columns``: ``COLUMNS`` if set, else the width of the
    terminal on stdout, else 80; without importing :mod:`shutil`, which imports bz2 and lzma
    (~2 ms of each start: argparse makes a formatter, and asks this, at every flag added)."""
    try:
        columns = int(os.environ["COLUMNS"])
    except (KeyError, ValueError):
        columns = 0
    if columns <= 0:
        try:
            columns = os.get_terminal_size(sys.__stdout__.fileno()).columns  # type: ignore[union-attr]
        except (AttributeError, ValueError, OSError):
            columns = 0
        columns = columns or 80
    return columns


class _Help(argparse.HelpFormatter):
    """Every option's help ends with its default (unless it has none or says it already)."""

    def __init__(
        self,
        prog: str,
        indent_increment: int = 2,
        max_help_position: int = 24,
        width: int | None = None,
    ) -> None:
        # argparse's own default width, from _terminal_columns
        width = _terminal_columns() - 2 if width is None else width
        super().__init__(prog, indent_increment, max_help_position, width)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            "(default" in text
            or default is None
            or default is False
            or default == argparse.SUPPRESS
            or action.nargs == 0
        ):
            return text
        shown = ", ".join(str(v) for v in default) if isinstance(default, list) else default
        return f"{text} (default: {shown})"


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one line on stderr (exit 2), not a usage dump.

    Subcommand parsers inherit the class (``add_subparsers`` uses ``type(self)``)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", _Help)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or with ``only`` of that command alone (the others
    listed, without their flags): a run builds the flags of its own command only and imports
    only what they name (:func:`main`)."""
    p = _Parser(
        prog="bdsfix",
        description="Real-time BeiDou receiver service with the a-priori-free fast first fix "
        "(Zhao, Cui & Lu). Each command's options: bdsfix COMMAND --help; the record, NMEA "
        "and ZeroMQ contracts: docs/architecture.md in the repository.",
    )
    p.add_argument("--version", action="version", version=f"bdsfix {__version__}")
    p.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)"
    )
    # -v is also taken after the subcommand (bdsfix solve -v ...)
    verbose = _Parser(add_help=False)
    verbose.add_argument(
        "-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output"
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, summary: str, description: str) -> argparse.ArgumentParser:
        parser: argparse.ArgumentParser = sub.add_parser(
            name, help=summary, description=description, parents=[verbose]
        )
        return parser

    s = command(
        "solve",
        "batch per-epoch solutions from RINEX 3/4 obs (or a GnssLogger log) + nav",
        "Solve every epoch of a RINEX 3 or 4 observation file (or an Android GnssLogger log) "
        "with the fast fix and/or SPP and "
        "write one record per epoch and solver; a summary with the decline reasons goes "
        "to stderr.",
    )
    if only in (None, "solve"):
        _solve_flags(s)
    c = command(
        "coverage",
        "usability study of the fast fix (paper Table 3)",
        "Where and how often the fast fix is usable: at least 4 GEOs in view and the GEO "
        "GDOP gate passed, over a global grid and a span of days, from the paper's Table 1 "
        "constellation or a nav file's GEOs.",
    )
    if only in (None, "coverage"):
        _coverage_flags(c)
    r = command(
        "replay",
        "replay a capture (or the built-in scenario) as a receiver",
        "Feed a capture through the same stream path as the daemon: a UBX/RTCM3/SBF/NMEA "
        "capture, a RINEX 3/4 obs file or an Android GnssLogger log, paced in real time "
        "(--max-speed: as fast as "
        "possible); with no FILE, the built-in virtual receiver near Beijing at full speed. "
        "NMEA goes to stdout unless another output is asked for; a summary to stderr.",
    )
    if only in (None, "replay"):
        _replay_flags(r)
    d = command(
        "run",
        "the daemon (config file; every key is also a flag)",
        "The receiver daemon: reads a receiver (serial, TCP or a file), publishes NMEA on "
        "TCP, ZeroMQ and files, keeps its ephemeris store in the state directory. Every key "
        "of the TOML config is also a flag; flags override the file.",
    )
    if only in (None, "run"):
        _run_flags(d)
    m = command(
        "simulate",
        "virtual receiver (BeiDou; GPS and Galileo with --nav): UBX out",
        "A virtual receiver at a known place (BeiDou B1I; GPS L1 C/A and Galileo E1 from a "
        "real nav file with --nav and --systems): UBX RXM-MEASX, RXM-RAWX (prMes valid once "
        "each satellite's time of week decoded) and RXM-SFRBX with real subframe timing, to "
        "a file, stdout or a pty.",
    )
    if only in (None, "simulate"):
        _simulate_flags(m)
    t = command(
        "ttff",
        "time to first fix: fast vs conventional on restarts",
        "Time to first fix after receiver restarts: emulated on real RINEX data (OBS NAV), "
        "or (--simulate) restarts of the virtual receiver streamed through a pty into "
        "'bdsfix run'. Fast fix versus conventional SPP and GEO-only SPP.",
    )
    if only in (None, "ttff"):
        _ttff_flags(t)
    g = command(
        "configure",
        "set a u-blox receiver up for the fast fix",
        "Set a u-blox receiver up for the fast fix with pyubx2's CFG messages: BeiDou B1I on "
        "with its GEOs, RXM-RAWX, RXM-MEASX and RXM-SFRBX on the port in use, the "
        "measurement rate (M8: CFG-GNSS, CFG-RATE, CFG-MSG; F9/X20: CFG-VALSET). Each "
        "message waits for its ACK/NAK; a refusal (exit 5) or no answer (exit 3) is one "
        "line naming what is in effect. 'bdsfix run' does the same with configure = true.",
    )
    if only in (None, "configure"):
        _configure_flags(g)
    z = command(
        "sub",
        "print ZeroMQ messages",
        "Subscribe to a bdsfix ZeroMQ PUB endpoint and print each message as "
        "'TOPIC JSON' (a running 'bdsfix run', or 'bdsfix replay --zmq ENDPOINT'); "
        "--json prints the JSON alone.",
    )
    if only in (None, "sub"):
        _sub_flags(z)
    return p


def _solve_flags(s: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix solve``."""
    from service.core.settings import add_flags
    from service.core.systems import SystemsConfig
    from service.engine.coarse import CoarseConfig
    from service.engine.solver import SolverConfig

    s.add_argument(
        "obs",
        help="RINEX 3/4 observation file (BeiDou C2I/C1I, GPS C1C, Galileo C1C/C1X/C1B "
        "pseudoranges, as --systems asks) or Android GnssLogger log (FORMAT:PATH names the "
        "format)",
    )
    s.add_argument("nav", nargs="+", help="one or more RINEX 3/4 nav files")
    s.add_argument(
        "--mode",
        choices=["fast", "spp", "both"],
        default="both",
        help="which solver runs on each epoch",
    )
    s.add_argument(
        "--fractional",
        choices=["non-geo", "none"],
        default="non-geo",
        help="non-geo: the fast solver sees non-GEO pseudoranges only modulo c*T, as in the "
        "paper; none: every range full",
    )
    s.add_argument(
        "--period-ms",
        type=int,
        choices=[1, 20],
        default=None,
        help="T of the fractional ranges [ms]: 1 or 20 (D1 bit); default each satellite "
        "system's code period (1 for B1I)",
    )
    s.add_argument(
        "--format", choices=["jsonl", "csv", "nmea"], default="jsonl", help="output format"
    )
    s.add_argument("--out", default="-", help="output file, - for stdout")
    add_flags(s, SolverConfig, "solver")
    add_flags(s, SystemsConfig, "systems")
    add_flags(
        s, CoarseConfig, "coarse-time first fix (fast solver; fewer full ranges than unknowns)"
    )


def _coverage_flags(c: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix coverage``."""
    from service.commands.options import add_start_flag

    c.add_argument(
        "--days", type=float, default=None, help="span of the study [days] (8; --first-fix: 1)"
    )
    c.add_argument(
        "--step-s", type=float, default=None, help="time step [s] (300; --first-fix: 600)"
    )
    c.add_argument(
        "--grid-deg", type=float, default=None, help="grid spacing [deg] (1; --first-fix: 2)"
    )
    c.add_argument(
        "--first-fix",
        action="store_true",
        help="compare the paper's method with the coarse-time first fix (>= 6 BeiDou "
        "satellites above the mask) over the surface x time, every satellite of Table 1 or "
        "of --nav",
    )
    c.add_argument(
        "--solve-grid-deg",
        type=float,
        default=0.0,
        help="--first-fix with --nav: also run the coarse-time solver on simulated first "
        "epochs on a grid this coarse [deg] (0: off)",
    )
    c.add_argument(
        "--solve-epochs",
        type=int,
        default=4,
        help="--solve-grid-deg: epochs spread over the span",
    )
    c.add_argument(
        "--altitudes-m",
        type=_float_list,
        default=[0.0, 1_000_000.0],
        help="user altitudes, comma-separated [m]",
    )
    c.add_argument("--beta", type=float, default=3000.0, help="GEO GDOP gate beta (eq. 21)")
    c.add_argument(
        "--elmask-deg",
        type=float,
        default=None,
        help="elevation mask [deg] (0; --first-fix: the solver's 10)",
    )
    c.add_argument("--nav", help="RINEX nav file: broadcast constellation instead of Table 1")
    add_start_flag(c, "the study's first epoch (default: Table 1's, 2015-05-19T04:00:00)")
    c.add_argument("--json", dest="json_out", help="write the result as JSON to FILE (- stdout)")
    c.add_argument("--plot", help="write a coverage map PNG (needs the plot extra)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")


def _replay_flags(r: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix replay``."""
    from service.core.settings import add_flags
    from service.core.sow_rule import FullRuleConfig
    from service.core.systems import SystemsConfig
    from service.engine.coarse import CoarseConfig
    from service.engine.solver import SolverConfig
    from service.output.sinks import SINKS
    from service.output.sinks.base import HTTP_MAX_CLIENTS, NMEA_TCP_MAX_CLIENTS

    r.add_argument(
        "files",
        nargs="*",
        help="UBX/RTCM/SBF/NMEA capture, RINEX 3/4 obs or GnssLogger log (FORMAT:PATH, e.g. "
        "gnsslogger:log.txt, names the format); none: the built-in virtual receiver near "
        "Beijing",
    )
    r.add_argument(
        "--nav",
        action="append",
        help="RINEX 3/4 nav file(s): held ephemerides; with no FILE, the built-in virtual "
        "receiver flies their satellites (GPS and Galileo too with --systems) instead of Table 1",
    )
    r.add_argument(
        "--restart-at",
        type=float,
        default=None,
        metavar="SECONDS",
        help="emulate a receiver restart this many data seconds into the stream",
    )
    pace = r.add_mutually_exclusive_group()
    pace.add_argument(
        "--speed",
        type=float,
        default=None,
        help="pace by the data's timestamps at X times real time (files: 1)",
    )
    pace.add_argument(
        "--max-speed", action="store_true", help="as fast as possible (no pacing by data time)"
    )
    r.add_argument("--nmea-tcp", metavar="HOST:PORT", help="NMEA TCP server")
    r.add_argument(
        "--nmea-tcp-max-clients",
        type=_positive_int,
        default=NMEA_TCP_MAX_CLIENTS,
        metavar="N",
        help="NMEA TCP clients served at once; more are accepted and closed "
        f"(default {NMEA_TCP_MAX_CLIENTS})",
    )
    r.add_argument("--zmq", metavar="ENDPOINT", help="ZeroMQ PUB endpoint")
    r.add_argument("--nmea-out", metavar="FILE|-", help="NMEA to a file or stdout")
    r.add_argument("--jsonl-out", metavar="FILE|-", help="JSONL records to a file or stdout")
    r.add_argument(
        "--output",
        action="append",
        metavar="KIND:SPEC",
        help=f"another output (repeatable; kinds: {', '.join(SINKS)})",
    )
    r.add_argument(
        "--http-max-clients",
        type=_positive_int,
        default=HTTP_MAX_CLIENTS,
        metavar="N",
        help="status page (--output http:HOST:PORT): connections served at once; more are "
        f"accepted and closed (default {HTTP_MAX_CLIENTS})",
    )
    r.add_argument("--talker", choices=["GN", "GB", "BD", "GP"], default="GN", help="NMEA talker")
    r.add_argument("--seed", type=int, default=0, help="seed of emulated sync delays")
    r.add_argument(
        "--gps-week",
        type=int,
        default=None,
        help="GPS week hint for RTCM-only files (else the stream's own ephemerides give it)",
    )
    r.add_argument(
        "--status-interval-s", type=float, default=10.0, help="period of STATUS records [s]"
    )
    add_flags(r, FullRuleConfig, "restart (--restart-at and the built-in scenario)")
    add_flags(r, SolverConfig, "solver")
    add_flags(r, SystemsConfig, "systems (every input: UBX, RTCM3, SBF, RINEX, GnssLogger)")
    add_flags(r, CoarseConfig, "coarse-time first fix (fewer full ranges than unknowns)")


def _run_flags(d: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix run``."""
    from service.daemon.config import DEFAULT_CONFIG, add_config_flags

    d.add_argument(
        "--config", default=None, help=f"TOML config (default {DEFAULT_CONFIG} when it exists)"
    )
    add_config_flags(d)


def _simulate_flags(m: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix simulate``."""
    from service.commands.options import add_start_flag
    from service.core.settings import add_flags
    from service.core.sow_rule import FullRuleConfig
    from service.core.systems import SystemsConfig
    from service.output.sinks import SINKS

    m.add_argument("--nav", help="RINEX 3/4 nav file (default: the paper's Table 1 set)")
    add_flags(
        m,
        SystemsConfig,
        "systems (from --nav: GPS and Galileo satellites join, on their own LNAV/I/NAV timing)",
    )
    m.add_argument(
        "--measx-systems",
        default="C",
        metavar="LETTERS",
        help="the simulated systems whose RXM-MEASX code phases are written (default C; a "
        "real F9P writes every system: C,G,E), each also in --systems",
    )
    m.add_argument("--lat-deg", type=float, default=39.9, help="true latitude [deg]")
    m.add_argument("--lon-deg", type=float, default=116.4, help="true longitude [deg]")
    m.add_argument("--alt-m", type=float, default=50.0, help="true ellipsoidal height [m]")
    add_start_flag(m, "the first epoch (default: first toe, or Table 1's epoch)")
    m.add_argument("--duration-s", type=float, default=60.0, help="length of the stream [s]")
    m.add_argument("--rate-hz", type=float, default=10.0, help="measurement rate [Hz]")
    m.add_argument("--clock-offset-s", type=float, default=0.0123, help="receiver clock offset [s]")
    m.add_argument("--noise-m", type=float, default=1.3, help="pseudorange noise sigma [m]")
    m.add_argument("--seed", type=int, default=0, help="random seed (noise, sync delays)")
    dest = m.add_mutually_exclusive_group()
    dest.add_argument("--out", help="file, - for stdout (default)")
    dest.add_argument(
        "--pty",
        action="store_true",
        help="write to a new pty (path on stderr); the stream starts when a program opens it",
    )
    m.add_argument("--link", metavar="PATH", help="--pty: a symlink to the pty at PATH")
    m.add_argument("--realtime", action="store_true", help="pace file/stdout output in real time")
    m.add_argument(
        "--no-ephemerides",
        dest="ephemerides",
        action="store_false",
        help="do not start the stream with the ephemerides it was made with (RTCM 1042), so "
        "a replay must learn them from the subframes or a nav file",
    )
    m.add_argument(
        "--ephemerides-every-s",
        type=float,
        default=None,
        metavar="S",
        help="repeat the RTCM 1042 ephemerides this often, as a receiver repeats its "
        "navigation data (default: 1 with --pty, else only at the start; 0: only at the start)",
    )
    m.add_argument(
        "--max-speed", action="store_true", help="as fast as possible (no pacing by data time)"
    )
    m.add_argument(
        "--wait-config",
        action="store_true",
        help="with --pty: act as a u-blox receiver fresh from its defaults (GEOs unused, no "
        "UBX output) that answers CFG messages (ACK, NAK for what it does not support) and "
        "sends only the measurement messages it was asked for; a signal configuration "
        "restarts its tracking ('bdsfix configure' sets it up)",
    )
    m.add_argument(
        "--port",
        choices=["uart1", "uart2", "usb", "spi", "i2c"],
        default="uart1",
        help="--wait-config: the receiver port the pty stands for (output enabled on another "
        "port is acknowledged and not sent here)",
    )
    m.add_argument(
        "--nak",
        action="append",
        metavar="NAME",
        help="--wait-config, for tests: refuse (ACK-NAK) this configuration key "
        "(CFG_BDS_USE_GEO_PRN) or message (CFG-GNSS); repeatable",
    )
    m.add_argument(
        "--no-answer",
        action="store_true",
        help="--wait-config, for tests: never answer, as a receiver at another baud rate",
    )
    m.add_argument(
        "--output",
        action="append",
        metavar="KIND:SPEC",
        help="also solve the stream here and publish it (repeatable; kinds: "
        f"{', '.join(SINKS)}; e.g. http:127.0.0.1:8080, the status page)",
    )
    add_flags(m, FullRuleConfig, "prMes validity")


def _ttff_flags(t: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix ttff``."""
    from service.commands.options import add_start_flag
    from service.core.settings import add_flags
    from service.core.sow_rule import FullRuleConfig
    from service.core.systems import SystemsConfig
    from service.engine.solver import SolverConfig

    t.add_argument(
        "obs", nargs="?", help="RINEX 3/4 obs file or GnssLogger log (not with --simulate)"
    )
    t.add_argument("nav", nargs="*", help="RINEX 3 nav file(s)")
    t.add_argument("--trials", type=int, default=100, help="number of restarts")
    t.add_argument("--seed", type=int, default=1, help="random seed of the restart times")
    t.add_argument("--json", action="store_true", help="print the result as JSON")
    t.add_argument("--plot", help="TTFF histograms PNG")
    t.add_argument(
        "--compare-rules",
        action="store_true",
        help="also run the same restarts under the other --full-rule and report both",
    )
    t.add_argument(
        "--simulate",
        action="store_true",
        help="restarts of a virtual receiver streamed through a pty into 'bdsfix run' "
        "(NAV optional: Table 1 ephemerides by default)",
    )
    t.add_argument("--lat-deg", type=float, default=39.9, help="--simulate: true latitude")
    t.add_argument("--lon-deg", type=float, default=116.4, help="--simulate: true longitude")
    t.add_argument("--alt-m", type=float, default=50.0, help="--simulate: true height")
    t.add_argument("--rate-hz", type=float, default=10.0, help="--simulate: measurement rate")
    t.add_argument("--noise-m", type=float, default=1.3, help="--simulate: range noise sigma")
    t.add_argument("--trial-s", type=float, default=13.0, help="--simulate: stream per trial")
    add_start_flag(t, "--simulate: the first restart (default: 10 min after the nav toe)")
    t.add_argument(
        "--max-eph-age-s",
        type=float,
        default=7200.0,
        help="--simulate: satellites whose ephemeris is older are not simulated; the daemon "
        "gets the same limit",
    )
    t.add_argument(
        "--coarse-fix",
        action="store_true",
        help="--simulate: the daemon also runs the coarse-time first fix (fewer than 4 full "
        "GEO ranges); its fixes count as fast",
    )
    add_flags(t, FullRuleConfig, "restart")
    add_flags(t, SolverConfig, "solver")
    add_flags(t, SystemsConfig, "systems (--simulate with --nav: GPS and Galileo satellites join)")


def _configure_flags(g: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix configure``."""
    from service.core.receiver_setup import ReceiverSetup
    from service.core.settings import add_flags

    g.add_argument(
        "--source",
        metavar="DEVICE",
        help="the receiver: /dev/ttyX or serial:DEV[:BAUD] (also the pty of 'bdsfix "
        "simulate --pty --wait-config'); not needed with --dry-run",
    )
    g.add_argument("--baud", type=_positive_int, default=115200, help="serial baud rate")
    add_flags(g, ReceiverSetup)
    g.add_argument(
        "--save",
        action="store_true",
        help="once every message is acknowledged, save the set-up to BBR and flash",
    )
    g.add_argument(
        "--dry-run",
        action="store_true",
        help="print the messages (hex, then what each asks) instead of sending them",
    )


def _sub_flags(z: argparse.ArgumentParser) -> None:
    """The flags of ``bdsfix sub``."""
    z.add_argument(
        "endpoint", nargs="?", default="tcp://127.0.0.1:10111", help="ZeroMQ PUB endpoint"
    )
    z.add_argument(
        "--topic",
        action="append",
        help="FIX, SKY, TRACK or STATUS, in any case; repeatable (default all)",
    )
    z.add_argument(
        "--json",
        action="store_true",
        help="print the JSON record alone, one per line (for jq), without the topic",
    )
    z.add_argument("--count", type=int, default=None, help="exit after N messages")
    z.add_argument("--timeout-s", type=float, default=None, help="exit after this idle time")
    z.add_argument("--curve-server-key", metavar="FILE", help="CURVE: server public certificate")
    z.add_argument("--curve-key", metavar="FILE", help="CURVE: this client's secret certificate")


def _resolve(spec: str) -> Callable[[argparse.Namespace], int]:
    module, func = spec.split(":")
    handler: Callable[[argparse.Namespace], int] = getattr(importlib.import_module(module), func)
    return handler


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names: its first word that is not an option (the options
    before it, ``-v``, ``-h`` and ``--version``, take no value); None when that is no
    command (argparse then says so, with every command's parser built)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in _HANDLERS else None


def main(argv: Sequence[str] | None = None, *, program: bool = False) -> int:
    """Run the command ``argv`` names (default: the process's arguments); its exit code.

    ``program`` (:func:`entry`, the process is bdsfix): the cyclic garbage collector is off
    from the start, and what the parser and the command's modules imported is frozen out
    of its reach (:func:`gc.freeze`) before it is switched on for the command itself.
    Imports make a few hundred thousand objects, nearly none of them garbage, and the
    collector's automatic passes over them were ~50 per start of ``bdsfix solve``; the
    daemon's loop and the batch solver freeze their start-up heap as well, the first after
    a full collection that then has nothing of it to walk."""
    # the flags of the command run only: building every command's parser imported the
    # configuration of them all (the daemon's, the outputs', the coarse-time solver's)
    parser = build_parser(_command_of(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(
        level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        handler = _resolve(_HANDLERS[args.command])
        if program:
            gc.freeze()
            gc.enable()
        return handler(args)
    except BdsfixError as exc:
        # exit codes: service/core/errors.py (EXIT_*) and the README's "Exit codes"
        print(f"bdsfix {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        return EXIT_OK
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception as exc:  # a bug: still one line; the traceback only with -v
        if args.verbose:
            traceback.print_exc()
        print(
            f"bdsfix {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)}"
            + ("" if args.verbose else " (-v shows the traceback)"),
            file=sys.stderr,
        )
        return EXIT_INTERNAL


def entry() -> NoReturn:
    """The ``bdsfix`` program (the console script, ``python -m service``): :func:`main` on
    the process's arguments, then exit with its code.

    What is left when it returns is moved out of the cyclic garbage collector's reach
    (:func:`gc.freeze`) before the interpreter shuts down: the shutdown otherwise runs a full
    collection over every object the run imported or made (numpy's and bdsfix's modules,
    the navigation), 10-20 ms of each start of ``bdsfix solve`` on a 2-core machine, to free
    memory the process is about to hand back whole. Every command has closed what it opened
    by then (outputs, sockets), and the shutdown still flushes stdout/stderr and runs the
    ``atexit`` handlers; only objects in reference cycles are left unfinalized.

    The collector is off until the command starts (:func:`main`, ``program``)."""
    gc.disable()
    code = main(program=True)
    gc.freeze()
    sys.exit(code)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).splitlines()) or type(exc).__name__


if __name__ == "__main__":
    entry()
