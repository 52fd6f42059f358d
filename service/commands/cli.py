"""The ``bdsfix`` command line (contract in docs/architecture.md): the parser and the
dispatch to one module per subcommand; only this entry point configures logging."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
from collections.abc import Callable, Sequence
from typing import NoReturn

from service import __version__
from service.commands.options import add_start_flag
from service.core.errors import EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, BdsfixError
from service.core.settings import add_flags
from service.daemon.config import DEFAULT_CONFIG, add_config_flags
from service.engine.solver import SolverConfig
from service.output.sinks import SINKS
from service.output.sinks.base import NMEA_TCP_MAX_CLIENTS

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
}


def _float_list(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from exc


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

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="bdsfix",
        description="Real-time BeiDou receiver service with the a-priori-free fast first fix "
        "(Zhao, Cui & Lu). Each command's options: bdsfix COMMAND --help; the record, NMEA "
        "and ZeroMQ contracts: docs/architecture.md in the repository.",
    )
    p.add_argument("--version", action="version", version=f"bdsfix {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("solve", help="batch per-epoch solutions from RINEX 3 obs + nav")
    s.add_argument("obs")
    s.add_argument("nav", nargs="+", help="one or more RINEX 3 nav files")
    s.add_argument("--mode", choices=["fast", "spp", "both"], default="both")
    s.add_argument("--fractional", choices=["non-geo", "none"], default="non-geo")
    s.add_argument("--period-ms", type=int, choices=[1, 20], default=1)
    s.add_argument("--format", choices=["jsonl", "csv", "nmea"], default="jsonl")
    s.add_argument("--out", default="-", help="output file, - for stdout")
    add_flags(s, SolverConfig, "solver")

    c = sub.add_parser("coverage", help="usability study of the fast fix (paper Table 3)")
    c.add_argument("--days", type=float, default=8.0)
    c.add_argument("--step-s", type=float, default=300.0)
    c.add_argument("--grid-deg", type=float, default=1.0)
    c.add_argument("--altitudes-m", type=_float_list, default=[0.0, 1_000_000.0])
    c.add_argument("--beta", type=float, default=3000.0)
    c.add_argument("--elmask-deg", type=float, default=0.0)
    c.add_argument("--nav", help="RINEX nav file: broadcast constellation instead of Table 1")
    add_start_flag(c, "the study's first epoch (default: Table 1's, 2015-05-19T04:00:00)")
    c.add_argument("--json", dest="json_out", help="write the result as JSON to FILE (- stdout)")
    c.add_argument("--plot", help="write a coverage map PNG (needs the plot extra)")
    c.add_argument("--no-progress", action="store_true")

    r = sub.add_parser("replay", help="replay a capture (or the built-in scenario) as a receiver")
    r.add_argument(
        "files",
        nargs="*",
        help="UBX/RTCM/NMEA capture or RINEX 3 obs; none: the "
        "built-in virtual receiver near Beijing",
    )
    r.add_argument("--nav", action="append", help="RINEX 3 nav file(s): held ephemerides")
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
    r.add_argument("--talker", choices=["GN", "GB", "BD", "GP"], default="GN")
    r.add_argument("--seed", type=int, default=0, help="seed of emulated sync delays")
    r.add_argument("--gps-week", type=int, default=None, help="GPS week for RTCM-only files")
    r.add_argument("--status-interval-s", type=float, default=10.0)
    add_flags(r, SolverConfig, "solver")

    d = sub.add_parser("run", help="the daemon (config file; every key is also a flag)")
    d.add_argument(
        "--config", default=None, help=f"TOML config (default {DEFAULT_CONFIG} when it exists)"
    )
    add_config_flags(d)

    m = sub.add_parser("simulate", help="virtual BDS receiver: UBX out")
    m.add_argument("--nav", help="RINEX 3 nav file (default: the paper's Table 1 set)")
    m.add_argument("--lat-deg", type=float, default=39.9)
    m.add_argument("--lon-deg", type=float, default=116.4)
    m.add_argument("--alt-m", type=float, default=50.0)
    add_start_flag(m, "the first epoch (default: first toe, or Table 1's epoch)")
    m.add_argument("--duration-s", type=float, default=60.0)
    m.add_argument("--rate-hz", type=float, default=10.0)
    m.add_argument("--clock-offset-s", type=float, default=0.0123)
    m.add_argument("--noise-m", type=float, default=1.3)
    m.add_argument("--seed", type=int, default=0)
    dest = m.add_mutually_exclusive_group()
    dest.add_argument("--out", help="file, - for stdout (default)")
    dest.add_argument("--pty", action="store_true", help="write to a new pty (path on stderr)")
    m.add_argument("--realtime", action="store_true", help="pace file/stdout output in real time")
    m.add_argument(
        "--max-speed", action="store_true", help="as fast as possible (no pacing by data time)"
    )

    t = sub.add_parser("ttff", help="time to first fix: fast vs conventional on restarts")
    t.add_argument("obs", nargs="?")
    t.add_argument("nav", nargs="*")
    t.add_argument("--trials", type=int, default=100)
    t.add_argument("--seed", type=int, default=1)
    t.add_argument("--json", action="store_true", help="print the result as JSON")
    t.add_argument("--plot", help="TTFF histograms PNG")
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
    add_flags(t, SolverConfig, "solver")

    z = sub.add_parser("sub", help="print ZeroMQ messages")
    z.add_argument("endpoint", nargs="?", default="tcp://127.0.0.1:10111")
    z.add_argument("--topic", action="append", help="FIX, SKY, TRACK or STATUS (default all)")
    z.add_argument("--count", type=int, default=None, help="exit after N messages")
    z.add_argument("--timeout-s", type=float, default=None, help="exit after this idle time")
    z.add_argument("--curve-server-key", metavar="FILE", help="CURVE: server public certificate")
    z.add_argument("--curve-key", metavar="FILE", help="CURVE: this client's secret certificate")
    return p


def _resolve(spec: str) -> Callable[[argparse.Namespace], int]:
    module, func = spec.split(":")
    handler: Callable[[argparse.Namespace], int] = getattr(importlib.import_module(module), func)
    return handler


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(
        level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return _resolve(_HANDLERS[args.command])(args)
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


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).splitlines()) or type(exc).__name__


if __name__ == "__main__":
    raise SystemExit(main())
