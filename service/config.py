"""Daemon configuration: a TOML file (tomllib) whose every key is also a command-line flag.

The keys, their types, defaults and help live in one table (:data:`FIELDS`); the file parser,
the flag parser and the validation are all driven by it. Unknown keys, wrong types and bad
values raise :class:`~service.errors.ConfigError` with one line naming the file and key.
"""

from __future__ import annotations

import argparse
import math
import os
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from service.errors import ConfigError

DEFAULT_CONFIG = "/etc/bdsfix/bdsfix.toml"


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """Settings of ``bdsfix run`` (defaults: loopback-only outputs)."""

    source: str = ""
    baud: int = 115200
    nav: tuple[str, ...] = ()
    state_dir: str = ""
    nmea_tcp: str = "127.0.0.1:10110"
    nmea_out: str = ""
    nmea_serial: str = ""
    talker: str = "GN"
    zmq: str = "tcp://127.0.0.1:10111"
    zmq_curve_secret_key: str = ""
    zmq_curve_clients: str = ""
    jsonl_out: str = ""
    elmask_deg: float = 10.0
    beta: float = 0.0
    range_error_m: float = 50.0
    iono: str = "auto"
    tropo: bool = True
    max_eph_age_s: float = 7200.0
    status_interval_s: float = 10.0
    store_save_interval_s: float = 60.0
    log_level: str = "info"

    def resolved_state_dir(self) -> Path:
        return Path(self.state_dir or os.environ.get("BDSFIX_STATE_DIR", "") or "bdsfix-state")


HELP: dict[str, str] = {
    "source": "receiver: /dev/ttyX, serial:DEV[:BAUD], tcp:HOST:PORT or a capture file",
    "baud": "serial baud rate",
    "nav": "RINEX 3 nav file(s) loaded into the ephemeris store at start",
    "state_dir": "directory of the persisted ephemeris store ($BDSFIX_STATE_DIR)",
    "nmea_tcp": "NMEA TCP server HOST:PORT ('' disables)",
    "nmea_out": "NMEA to a file or - for stdout",
    "nmea_serial": "NMEA to a serial device or pty",
    "talker": "NMEA talker: GN, GB, BD or GP",
    "zmq": "ZeroMQ PUB endpoint ('' disables)",
    "zmq_curve_secret_key": "ZeroMQ CURVE: server secret certificate file ('' = no CURVE)",
    "zmq_curve_clients": "ZeroMQ CURVE: directory of allowed client public certificates "
    "('' = any client that knows the server key)",
    "jsonl_out": "JSONL records to a file or - for stdout",
    "elmask_deg": "elevation mask [deg]",
    "beta": "GDOP gate (0: derive from T and range_error_m)",
    "range_error_m": "assumed 3-sigma range error for the gate [m]",
    "iono": "ionosphere model: auto, bds, gps or off",
    "tropo": "Saastamoinen troposphere",
    "max_eph_age_s": "oldest usable ephemeris, |t - toe| [s]",
    "status_interval_s": "period of STATUS messages [s]",
    "store_save_interval_s": "shortest period between saves of a changed ephemeris store [s]",
    "log_level": "debug, info, warning or error",
}

CHOICES: dict[str, tuple[str, ...]] = {
    "talker": ("GN", "GB", "BD", "GP"),
    "iono": ("auto", "bds", "gps", "off"),
    "log_level": ("debug", "info", "warning", "error"),
}

# Numeric keys and the (low, high, what) they must satisfy; NaN never passes.
LIMITS: dict[str, tuple[float, float, str]] = {
    "baud": (1, 4_000_000, "a baud rate in 1..4000000"),
    "elmask_deg": (0.0, 90.0, "in [0, 90)"),
    "beta": (0.0, math.inf, ">= 0"),
    "range_error_m": (1e-9, math.inf, "> 0"),
    "max_eph_age_s": (1e-9, math.inf, "> 0"),
    "status_interval_s": (1e-3, 86400.0, "between 0.001 and 86400"),
    "store_save_interval_s": (0.0, 86400.0, "between 0 and 86400"),
}


def _within(name: str, value: Any) -> bool:
    low, high, _ = LIMITS[name]
    if name == "elmask_deg":
        return low <= value < high
    return low <= value <= high  # False for NaN


_TYPES: dict[str, type] = {"str": str, "int": int, "float": float, "bool": bool}


def _kind(name: str) -> str:
    ann = {f.name: f.type for f in fields(DaemonConfig)}[name]
    text = ann if isinstance(ann, str) else getattr(ann, "__name__", str(ann))
    return "list" if text.startswith("tuple") else text


def _coerce(name: str, value: Any, where: str) -> Any:
    kind = _kind(name)
    if kind == "list":
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: key '{name}' must be a list of strings")
        return tuple(value)
    want = _TYPES[kind]
    if kind == "float" and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, want) or (want is not bool and isinstance(value, bool)):
        raise ConfigError(
            f"{where}: key '{name}' must be {kind}, got {type(value).__name__} {value!r}"
        )
    if name in CHOICES and value not in CHOICES[name]:
        raise ConfigError(f"{where}: key '{name}' must be one of {', '.join(CHOICES[name])}")
    if name in LIMITS and not _within(name, value):
        raise ConfigError(f"{where}: key '{name}' must be {LIMITS[name][2]}, got {value!r}")
    return value


def load_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> DaemonConfig:
    """Read ``path`` (None: defaults only) and apply command-line ``overrides``."""
    values: dict[str, Any] = {}
    known = {f.name for f in fields(DaemonConfig)}
    if path is not None:
        p = Path(path)
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise ConfigError(f"{p}: config file not found") from exc
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read config: {exc.strerror}") from exc
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{p}: not valid TOML: {exc}") from exc
        for key, value in doc.items():
            if key not in known:
                raise ConfigError(f"{p}: unknown key '{key}'")
            values[key] = _coerce(key, value, str(p))
    for key, value in (overrides or {}).items():
        if value is not None:
            values[key] = _coerce(key, value, f"--{key.replace('_', '-')}")
    return DaemonConfig(**values)


def _parse_bool(text: str) -> bool:
    low = text.lower()
    if low in ("1", "true", "yes", "on"):
        return True
    if low in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per config key (default None, so the file's value stands unless given)."""
    for f in fields(DaemonConfig):
        flag = "--" + f.name.replace("_", "-")
        kind = _kind(f.name)
        kw: dict[str, Any] = {"dest": f.name, "default": None, "help": HELP.get(f.name, "")}
        if kind == "list":
            kw["action"] = "append"
        elif kind == "bool":
            kw["type"] = _parse_bool
        else:
            kw["type"] = _TYPES[kind]
        if f.name in CHOICES:
            kw["choices"] = CHOICES[f.name]
        parser.add_argument(flag, **kw)


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return {f.name: getattr(args, f.name, None) for f in fields(DaemonConfig)}
