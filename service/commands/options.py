"""The solver options every command shares: one builder of :class:`SolverConfig` from the
flags of :func:`service.core.settings.add_flags`."""

from __future__ import annotations

import argparse
import datetime as dt
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.core.errors import ConfigError, InputError
from service.core.files import PLOT_HINT
from service.core.settings import build, given
from service.core.sow_rule import FullRuleConfig
from service.core.systems import SystemsConfig, parse_systems
from service.engine.solver import SolverConfig

if TYPE_CHECKING:  # imported where built: a command without the coarse-time solver skips it
    from service.engine.coarse import CoarseConfig


def solver_config(args: argparse.Namespace, **overrides: Any) -> SolverConfig:
    """The :class:`service.engine.solver.SolverConfig` of a command's solver flags (the one
    builder every command uses); ``overrides`` are settings the command fixes itself."""
    return build(SolverConfig, given(args, SolverConfig) | overrides, {})


def systems_of(args: argparse.Namespace) -> frozenset[str]:
    """``--systems`` (:class:`service.core.systems.SystemsConfig`): the RINEX letters of the
    systems to position with; every system the input carries unless given."""
    return parse_systems(build(SystemsConfig, given(args, SystemsConfig), {}).systems)


def coarse_config(args: argparse.Namespace) -> CoarseConfig:
    """The :class:`service.engine.coarse.CoarseConfig` of a command's coarse-time flags."""
    from service.engine.coarse import CoarseConfig

    return build(CoarseConfig, given(args, CoarseConfig), {})


def full_rule(args: argparse.Namespace) -> str:
    """``--full-rule`` (:class:`service.core.sow_rule.FullRuleConfig`): when a (re)started
    receiver knows a satellite's time; ``sow`` unless given."""
    return build(FullRuleConfig, given(args, FullRuleConfig), {}).full_rule


def add_start_flag(parser: argparse.ArgumentParser | Any, what: str) -> None:
    """``--start ISO``: the one spelling of a start time (UTC) in every command."""
    parser.add_argument("--start", metavar="ISO", help=f"ISO 8601 UTC start: {what}")


def parse_start(text: str) -> dt.datetime:
    """``--start`` as a naive UTC datetime (an offset or ``Z`` is converted to UTC)."""
    try:
        t = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError as exc:
        raise ConfigError(f"--start {text!r} is not an ISO 8601 UTC date-time") from exc
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC).replace(tzinfo=None)
    return t


def check_output_path(path: str | None, flag: str) -> None:
    """An output file a command will write after long work can be written: its directory
    exists and is writable and it is not a directory (InputError, exit 3, before any
    computing); ``-`` (stdout) and None pass."""
    if not path or path == "-":
        return
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise InputError(f"{flag} {path}: is a directory")
    if not folder.is_dir():
        raise InputError(f"{flag} {path}: no such directory {folder}")
    if not os.access(folder, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise InputError(f"{flag} {path}: permission denied")


def check_plot(path: str | None) -> None:
    """``--plot PATH`` asked for: its directory is writable (:func:`check_output_path`) and
    matplotlib imports, checked before any computing (ConfigError, exit 2, with the hint)."""
    if not path:
        return
    check_output_path(path, "--plot")
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise ConfigError(PLOT_HINT) from exc


def check_range(flag: str, value: float, low: float, high: float) -> None:
    """``low <= value <= high`` (and not NaN), else ConfigError naming the flag (exit 2)."""
    if not low <= value <= high:
        raise ConfigError(f"{flag} must be in [{low:g}, {high:g}], got {value}")
