"""The solver options every command shares: one builder of :class:`SolverConfig` from the
flags of :func:`service.core.settings.add_flags`."""

from __future__ import annotations

import argparse
from typing import Any

from service.core.settings import build, given
from service.engine.solver import SolverConfig


def solver_config(args: argparse.Namespace, **overrides: Any) -> SolverConfig:
    """The :class:`service.engine.solver.SolverConfig` of a command's solver flags (the one
    builder every command uses); ``overrides`` are settings the command fixes itself."""
    return build(SolverConfig, given(args, SolverConfig) | overrides, {})
