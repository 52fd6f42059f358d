"""Settings as data: a dataclass field declared with :func:`setting` carries its help text,
type and allowed values, so that one routine turns it into a TOML key, a command-line flag
and a validation (:mod:`service.options`).

A field's name is its TOML key; its flag is the name with dashes (``elmask_deg`` ->
``--elmask-deg``). Fields without this metadata are internal (not settable by a user).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True, slots=True)
class Setting:
    """What a user may set: help, type (``str int float bool list``), allowed values."""

    help: str
    kind: str
    choices: tuple[str, ...] = ()
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False

    def allowed(self, value: Any) -> bool:
        """Within [low, high] (open ends as declared); always False for NaN."""
        if self.kind not in ("int", "float"):
            return not self.choices or value in self.choices
        lo_ok = value > self.low if self.low_open else value >= self.low
        hi_ok = value < self.high if self.high_open else value <= self.high
        return bool(lo_ok and hi_ok)

    def describe(self) -> str:
        """The allowed values in words, for error messages and --help."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.low == -math.inf and self.high == math.inf:
            return f"a finite {self.kind}" if self.kind == "float" else f"an {self.kind}"
        if self.high == math.inf:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        left = "(" if self.low_open else "["
        right = ")" if self.high_open else "]"
        return f"in {left}{self.low:g}, {self.high:g}{right}"


def setting(
    default: Any,
    help: str,
    *,
    kind: str,
    choices: tuple[str, ...] = (),
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> Any:
    """A dataclass field that is a user setting (see the module docstring)."""
    meta = Setting(help, kind, choices, low, high, low_open, high_open)
    if isinstance(default, list | dict | set):
        raise TypeError("mutable defaults: use a tuple")
    return field(default=default, metadata={"setting": meta})
