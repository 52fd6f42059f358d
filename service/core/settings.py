"""Settings as data: a dataclass field declared with :func:`setting` carries its help text,
type and allowed values, so that one routine turns it into a TOML key, a command-line flag
and a validation (this module).

A field's name is its TOML key; its flag is the name with dashes (``elmask_deg`` ->
``--elmask-deg``). Fields without this metadata are internal (not settable by a user).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import Field, dataclass, field, fields
from typing import Any, TypeVar

from service.core.errors import ConfigError


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


T = TypeVar("T")
_PY = {"str": str, "int": int, "float": float, "bool": bool}
SHOWN_CHARS = 200
"""A bad value is echoed in at most this many characters (a config may hold megabytes)."""


def shown(value: Any) -> str:
    """``repr(value)`` cut to :data:`SHOWN_CHARS` characters, saying how long it was."""
    text = repr(value)
    if len(text) <= SHOWN_CHARS:
        return text
    return f"{text[:SHOWN_CHARS]}... ({len(text)} characters)"


def unknown_key_message(where: str, key: str, known: Iterable[str]) -> str:
    """``where: unknown key 'KEY'``, with the nearest known key when one is close
    (:func:`difflib.get_close_matches`): a misspelt key says what was meant."""
    import difflib  # here: only a misspelt key needs it, not every start of every command

    near = difflib.get_close_matches(key, sorted(known), n=1, cutoff=0.6)
    hint = f" (did you mean '{near[0]}'?)" if near else ""
    name = key if len(key) <= 60 else f"{key[:60]}..."
    return f"{where}: unknown key {name!r}{hint}"


def settings_of(cls: type) -> Iterator[tuple[Field[Any], Setting]]:
    """The user settings of a dataclass, in declaration order."""
    for f in fields(cls):
        meta = f.metadata.get("setting")
        if isinstance(meta, Setting):
            yield f, meta


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def coerce(name: str, meta: Setting, value: Any, where: str) -> Any:
    """``value`` checked (and ints widened to floats) for setting ``name``; ConfigError
    naming ``where`` and the key otherwise."""
    if meta.kind == "list":
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: key '{name}' must be a list of strings")
        return tuple(value)
    want = _PY[meta.kind]
    if meta.kind == "float" and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, want) or (want is not bool and isinstance(value, bool)):
        raise ConfigError(
            f"{where}: key '{name}' must be {meta.kind}, got {type(value).__name__} {shown(value)}"
        )
    if isinstance(value, float) and math.isnan(value):
        raise ConfigError(f"{where}: key '{name}' must be {meta.describe()}, got nan")
    if not meta.allowed(value):
        raise ConfigError(f"{where}: key '{name}' must be {meta.describe()}, got {shown(value)}")
    return value


def build(
    cls: type[T], values: Mapping[str, Any], where: str | Mapping[str, str], prefix: str = ""
) -> T:
    """An instance of ``cls`` from setting values (others keep their defaults).

    ``where`` names the origin in errors: one string, or one per key (file or flag). With
    ``prefix``, the keys of ``values`` are the settings' names with it (as errors name them)."""
    known = {prefix + f.name: meta for f, meta in settings_of(cls)}
    kw = {}
    for name, value in values.items():
        origin = where if isinstance(where, str) else where.get(name, flag(name))
        if name not in known:
            raise ConfigError(unknown_key_message(origin, name, known))
        kw[name.removeprefix(prefix)] = coerce(name, known[name], value, origin)
    return cls(**kw)


def _parse_bool(text: str) -> bool:
    low = text.lower()
    if low in ("1", "true", "yes", "on"):
        return True
    if low in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")


def add_flags(
    parser: argparse.ArgumentParser | Any, cls: type, title: str | None = None, prefix: str = ""
) -> None:
    """One flag per setting of ``cls`` (default None: not given); --help shows the default.

    ``prefix`` goes before each name (key ``configure_model``, flag ``--configure-model``)."""
    target = parser.add_argument_group(title) if title else parser
    for f, meta in settings_of(cls):
        kw: dict[str, Any] = {"dest": prefix + f.name, "default": None}
        shown: Any = f.default
        if meta.kind == "list":
            kw["action"] = "append"
            kw["metavar"] = "VALUE"
            shown = "none" if not shown else ", ".join(str(v) for v in shown)
        elif meta.kind == "bool":
            kw["type"] = _parse_bool
            kw["metavar"] = "BOOL"
        else:
            kw["type"] = _PY[meta.kind]
        if meta.choices:
            kw["choices"] = meta.choices
        if shown == "":
            shown = "''"
        kw["help"] = f"{meta.help} (default: {shown})"
        target.add_argument(flag(prefix + f.name), **kw)


def given(args: argparse.Namespace, cls: type, prefix: str = "") -> dict[str, Any]:
    """The settings of ``cls`` given on the command line (flags left at None are not), by
    their names with ``prefix`` (as :func:`add_flags` declared them)."""
    out = {}
    for f, _ in settings_of(cls):
        value = getattr(args, prefix + f.name, None)
        if value is not None:
            out[prefix + f.name] = value
    return out


def flags_of(cfg: Any) -> list[str]:
    """Command-line flags that reproduce the user settings of ``cfg`` (for a child ``bdsfix``)."""
    out: list[str] = []
    for f, _ in settings_of(type(cfg)):
        out += [flag(f.name), str(getattr(cfg, f.name))]
    return out
