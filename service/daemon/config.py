"""Daemon configuration: a TOML file (tomllib) whose every key is also a command-line flag.

The keys are the settings of :class:`DaemonConfig` (source, outputs, store, status), of
:class:`service.core.receiver_setup.ReceiverSetup` with the prefix ``configure_`` (the
receiver set-up run with ``configure = true``) and of
:class:`service.engine.solver.SolverConfig` (the solver, shared by every command) and of
:class:`service.engine.coarse.CoarseConfig` (the coarse-time first fix), declared
once with their help, type and allowed values; :mod:`service.core.settings` parses and
checks them. Unknown keys, wrong types and bad values raise
:class:`~service.core.errors.ConfigError` with one line naming the file or flag and the key
(an unknown key with the nearest known one, a bad value in at most
:data:`~service.core.settings.SHOWN_CHARS` characters).

The keys are flat: every key is at the top level of the file, as every key is a flag
(``elmask_deg = 10.0``, ``--elmask-deg 10``); a table (``[solver]``) is refused with that
hint.

The file is read within bounds before tomllib sees it (issue 23): at most
:data:`MAX_CONFIG_BYTES` (``--config /dev/zero`` is refused after 1 MiB, not read until
memory runs out), and :func:`toml_shape_problem` refuses nesting deeper than
:data:`MAX_NESTING` and dotted keys of more than :data:`MAX_KEY_PARTS` parts (tomllib
recurses on nesting, to a RecursionError, and takes quadratic time and memory in the parts
of a dotted key: over 11.8 GB for one key of 100,000 parts).
"""

from __future__ import annotations

import argparse
import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from service.core.errors import ConfigError
from service.core.ntripurl import NtripUrl, is_ntrip, looks_like_url, parse_ntrip_url
from service.core.receiver_setup import DAEMON_PREFIX, ReceiverSetup
from service.core.settings import (
    add_flags,
    build,
    given,
    setting,
    settings_of,
    unknown_key_message,
)
from service.core.systems import EVERY_SYSTEM, parse_systems
from service.engine.coarse import CoarseConfig
from service.engine.solver import SolverConfig
from service.output.sinks import SINKS
from service.output.sinks.base import HTTP_MAX_CLIENTS, NMEA_TCP_MAX_CLIENTS

DEFAULT_CONFIG = "/etc/bdsfix/bdsfix.toml"


STORE_NAME = "ephemeris.json"  # the ephemeris store in the state directory


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """Settings of ``bdsfix run`` (defaults: loopback-only outputs)."""

    source: str = setting(
        "", "receiver: /dev/ttyX, serial:DEV[:BAUD], tcp:HOST:PORT or a capture file", kind="str"
    )
    baud: int = setting(115200, "serial baud rate", kind="int", low=1, high=4_000_000)
    nav: tuple[str, ...] = setting(
        (),
        "RINEX 3 nav file(s) loaded into the ephemeris store at start, and/or NTRIP "
        "sources of broadcast ephemerides (RTCM 1042) read all along: "
        "ntrip://user:pass@host:port/MOUNT (a user without :pass takes "
        "$BDSFIX_NTRIP_PASSWORD)",
        kind="list",
    )
    ntrip_max_age_s: float = setting(
        7200.0,
        "refuse a network ephemeris whose t_oe is further than this from the receiver's "
        "time [s] (counted ntrip_stale)",
        kind="float",
        low=0.0,
        low_open=True,
    )
    ntrip_reconnect_max_s: float = setting(
        4.0,
        "longest wait between two attempts to reach an NTRIP caster [s] (backoff from 0.25 s)",
        kind="float",
        low=0.1,
        high=300.0,
    )
    ntrip_header_timeout_s: float = setting(
        10.0,
        "longest time for an NTRIP caster's whole answer header [s]; a slower answer is "
        "dropped and retried (counted ntrip_header_timeouts)",
        kind="float",
        low=0.1,
        high=300.0,
    )
    state_dir: str = setting(
        "", "directory of the persisted ephemeris store ($BDSFIX_STATE_DIR)", kind="str"
    )
    nmea_tcp: str = setting(
        "127.0.0.1:10110", "NMEA TCP server HOST:PORT ('' disables)", kind="str"
    )
    nmea_tcp_max_clients: int = setting(
        NMEA_TCP_MAX_CLIENTS,
        "NMEA TCP clients served at once; a connection over the cap is accepted and closed "
        "at once (counted as nmea_clients_refused)",
        kind="int",
        low=1,
        high=100_000,
    )
    nmea_out: str = setting("", "NMEA to a file or - for stdout", kind="str")
    nmea_serial: str = setting("", "NMEA to a serial device or pty", kind="str")
    talker: str = setting("GN", "NMEA talker", kind="str", choices=("GN", "GB", "BD", "GP"))
    zmq: str = setting("tcp://127.0.0.1:10111", "ZeroMQ PUB endpoint ('' disables)", kind="str")
    zmq_curve_secret_key: str = setting(
        "", "ZeroMQ CURVE: server secret certificate file ('' = no CURVE)", kind="str"
    )
    zmq_curve_clients: str = setting(
        "",
        "ZeroMQ CURVE: directory of allowed client public certificates ('' = any client that "
        "knows the server key)",
        kind="str",
    )
    jsonl_out: str = setting("", "JSONL records to a file or - for stdout", kind="str")
    output: tuple[str, ...] = setting(
        (), f"more outputs, KIND:SPEC each (kinds: {', '.join(SINKS)})", kind="list"
    )
    http_max_clients: int = setting(
        HTTP_MAX_CLIENTS,
        "status page (output http:HOST:PORT): connections served at once; one over the cap "
        "is accepted and closed at once (counted as http_clients_refused)",
        kind="int",
        low=1,
        high=10_000,
    )
    max_eph_age_s: float = setting(
        7200.0, "oldest usable ephemeris, |t - toe| [s]", kind="float", low=0.0, low_open=True
    )
    status_interval_s: float = setting(
        10.0, "period of STATUS messages [s]", kind="float", low=1e-3, high=86400.0
    )
    store_save_interval_s: float = setting(
        60.0,
        "shortest period between saves of a changed ephemeris store [s]",
        kind="float",
        low=0.0,
        high=86400.0,
    )
    silence_warn_s: float = setting(
        30.0,
        "warn (once per this interval) while the source sends nothing recognisable for this "
        "long [s]; 0: never",
        kind="float",
        low=0.0,
    )
    log_level: str = setting(
        "info", "log level", kind="str", choices=("debug", "info", "warning", "error")
    )
    configure: bool = setting(
        False,
        "set the u-blox receiver up before reading it, as 'bdsfix configure' does (serial "
        "sources; the configure_* keys; RAM only, nothing saved); a NAK or no answer stops "
        "the start",
        kind="bool",
    )
    systems: str = setting(
        EVERY_SYSTEM,
        "satellite systems to position with, RINEX letters separated by commas: C (BeiDou "
        "B1I), G (GPS L1 C/A), E (Galileo E1); by default every system the input carries",
        kind="str",
    )
    solver: SolverConfig = field(default_factory=SolverConfig)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    setup: ReceiverSetup = field(default_factory=ReceiverSetup)

    def resolved_state_dir(self) -> Path:
        return Path(self.state_dir or os.environ.get("BDSFIX_STATE_DIR", "") or "bdsfix-state")


MAX_CONFIG_BYTES = 1 << 20
"""Largest config file read [bytes] (the example file is 4 KB)."""
MAX_NESTING = 8
"""Deepest nesting of arrays, inline tables and table headers in a config file."""
MAX_KEY_PARTS = 8
"""Most parts of one dotted key (``a.b.c`` has 3)."""

_TOML_TOKEN = re.compile(
    r"""
      (?P<comment>\#[^\n]*)
    | (?P<string>"{3}(?:[^"\\]|\\.|"(?!""))*"{3,5}
        | '{3}(?:[^']|'(?!''))*'{3,5}
        | "(?:[^"\\\n]|\\.)*"
        | '[^'\n]*')
    | (?P<open>[\[{])
    | (?P<close>[\]}])
    | (?P<dot>\.)
    | (?P<quote>["'])
    | (?P<key>[A-Za-z0-9_\-]+|[ \t]+)
    | (?P<other>.)
    """,
    re.VERBOSE | re.DOTALL,
)
"""TOML's tokens as far as nesting and dotted keys go (TOML 1.0: comments, the four kinds of
string, brackets, dots); ``quote`` is a string that does not end (tomllib refuses the file
there, so the scan stops)."""


def toml_shape_problem(text: str) -> str | None:
    """Why ``text`` is too deep for tomllib (None if it is not): nesting of ``[`` and ``{``
    beyond :data:`MAX_NESTING`, or a dotted key of more than :data:`MAX_KEY_PARTS` parts
    (bare or quoted parts joined by dots, spaces between; any other token ends the key).
    One linear pass; strings are skipped whole, so what they hold counts for nothing."""
    depth = 0
    dots = 0
    for m in _TOML_TOKEN.finditer(text):
        kind = m.lastgroup
        if kind == "quote":
            return None  # an unterminated string: tomllib stops there
        if kind == "dot":
            dots += 1
            if dots >= MAX_KEY_PARTS:
                return f"a dotted key of more than {MAX_KEY_PARTS} parts"
        elif kind not in ("key", "string"):
            dots = 0
        if kind == "open":
            depth += 1
            if depth > MAX_NESTING:
                return f"nesting deeper than {MAX_NESTING} levels"
        elif kind == "close":
            depth = max(0, depth - 1)
    return None


def _read_toml(p: Path) -> dict[str, Any]:
    """The TOML document of ``p``, read within the bounds of the module docstring."""
    try:
        with p.open("rb") as fh:
            data = fh.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError as exc:
        raise ConfigError(f"{p}: config file not found") from exc
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror}") from exc
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{p}: config larger than {MAX_CONFIG_BYTES >> 20} MiB: not read")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: not UTF-8 (byte {exc.start})") from exc
    problem = toml_shape_problem(text)
    if problem is not None:
        raise ConfigError(f"{p}: not read: {problem}")
    import tomllib  # here: only a configuration file needs it, not every start of every command

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {str(exc)[:200]}") from exc
    except RecursionError as exc:  # the scan above should make this unreachable
        raise ConfigError(f"{p}: not read: nested too deeply") from exc


def load_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> DaemonConfig:
    """Read ``path`` (None: defaults only) and apply command-line ``overrides``."""
    values: dict[str, Any] = {}
    origin: dict[str, str] = {}
    daemon_keys = {f.name for f, _ in settings_of(DaemonConfig)}
    solver_keys = {f.name for f, _ in settings_of(SolverConfig)}
    coarse_keys = {f.name for f, _ in settings_of(CoarseConfig)}
    setup_keys = {DAEMON_PREFIX + f.name for f, _ in settings_of(ReceiverSetup)}
    known = daemon_keys | solver_keys | coarse_keys | setup_keys
    if path is not None:
        p = Path(path)
        for key, value in _read_toml(p).items():
            if key not in known:
                if isinstance(value, dict):
                    raise ConfigError(
                        f"{p}: [{key[:60]}] is a table, and bdsfix.toml has none: every key "
                        "is at the top level, as in systemd/bdsfix.toml (elmask_deg = 10.0, "
                        "not under [solver])"
                    )
                raise ConfigError(unknown_key_message(str(p), key, known))
            values[key] = value
            origin[key] = str(p)
    for key, value in (overrides or {}).items():
        if value is not None:
            values[key] = value
            origin[key] = "--" + key.replace("_", "-")
    solver = build(SolverConfig, {k: v for k, v in values.items() if k in solver_keys}, origin)
    coarse = build(CoarseConfig, {k: v for k, v in values.items() if k in coarse_keys}, origin)
    daemon = build(DaemonConfig, {k: v for k, v in values.items() if k in daemon_keys}, origin)
    setup_values = {k: v for k, v in values.items() if k in setup_keys}
    setup = build(ReceiverSetup, setup_values, origin, DAEMON_PREFIX)
    ntrip_sources(daemon)  # a malformed NTRIP URL is a configuration error (one line, exit 2)
    parse_systems(daemon.systems)  # so is an unknown system letter
    return _with_parts(daemon, solver, setup, coarse)


def ntrip_sources(cfg: DaemonConfig) -> list[NtripUrl]:
    """The NTRIP sources among ``nav``, parsed (ConfigError naming the URL redacted): every
    entry that looks like a URL, so that one of another scheme (``ntrips://``, ``http://``)
    is refused as a URL, never opened as a file whose error would show its password."""
    return [parse_ntrip_url(entry) for entry in cfg.nav if _is_url(entry)]


def _is_url(entry: str) -> bool:
    return is_ntrip(entry) or looks_like_url(entry)


def nav_files(cfg: DaemonConfig) -> list[str]:
    """The RINEX nav files among ``nav``."""
    return [entry for entry in cfg.nav if not _is_url(entry)]


def _with_parts(
    cfg: DaemonConfig,
    solver: SolverConfig,
    setup: ReceiverSetup,
    coarse: CoarseConfig | None = None,
) -> DaemonConfig:
    kw = {f.name: getattr(cfg, f.name) for f in fields(DaemonConfig)}
    kw["solver"] = solver
    kw["coarse"] = coarse if coarse is not None else CoarseConfig()
    kw["setup"] = setup
    return DaemonConfig(**kw)


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per config key (default None, so the file's value stands unless given)."""
    add_flags(parser, DaemonConfig, "daemon")
    add_flags(parser, ReceiverSetup, "receiver set-up (with configure = true)", DAEMON_PREFIX)
    add_flags(parser, SolverConfig, "solver")
    add_flags(parser, CoarseConfig, "coarse-time first fix (fewer full ranges than unknowns)")


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return (
        given(args, DaemonConfig)
        | given(args, ReceiverSetup, DAEMON_PREFIX)
        | given(args, SolverConfig)
        | given(args, CoarseConfig)
    )
