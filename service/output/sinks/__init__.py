"""The outputs: one :class:`~service.output.sinks.base.Sink` each, opened by kind from a
spec string through :data:`SINKS`.

A new output is a module here with a factory ``(spec, options) -> Sink`` and one line in
:data:`SINKS`; ``--output KIND:SPEC`` (key ``output``) then opens it.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable
from dataclasses import dataclass

from service.core.errors import ConfigError
from service.output.sinks.base import Sink, SinkFactory, SinkOptions

SINKS: dict[str, str] = {
    # kind: "module:factory", imported when an output of that kind is opened
    "nmea-tcp": "service.output.sinks.nmea_tcp:open_sink",
    "nmea-file": "service.output.sinks.lines:open_nmea_file",
    "nmea-serial": "service.output.sinks.nmea_serial:open_sink",
    "zmq": "service.output.sinks.zmq_pub:open_sink",
    "jsonl": "service.output.sinks.lines:open_jsonl",
    "http": "service.output.sinks.http_page:open_sink",
}


@dataclass(frozen=True, slots=True)
class OutputSpec:
    """One output asked for: a kind of :data:`SINKS` and its spec string."""

    kind: str
    spec: str

    @classmethod
    def parse(cls, text: str) -> OutputSpec:
        """``KIND:SPEC`` (``jsonl:fixes.jsonl``, ``nmea-tcp:127.0.0.1:10110``) or ConfigError."""
        kind, sep, spec = text.partition(":")
        if not sep or not spec:
            raise ConfigError(f"output {text!r}: expected KIND:SPEC")
        _target(kind)  # a known kind, checked without importing its module
        return cls(kind, spec)


def _target(kind: str) -> str:
    target = SINKS.get(kind)
    if target is None:
        raise ConfigError(f"unknown output kind {kind!r}: expected one of {', '.join(SINKS)}")
    return target


def factory(kind: str) -> SinkFactory:
    """The factory registered for ``kind``; ConfigError naming the known kinds otherwise."""
    module, name = _target(kind).split(":")
    opener: SinkFactory = getattr(importlib.import_module(module), name)
    return opener


def open_sinks(specs: Iterable[OutputSpec], options: SinkOptions | None = None) -> list[Sink]:
    """Open every output in order; when one fails, those already open are closed and its
    error (BindError, InputError or ConfigError) propagates."""
    opened: list[Sink] = []
    try:
        for out in specs:
            opened.append(factory(out.kind)(out.spec, options or SinkOptions()))
    except BaseException:
        for sink in opened:
            sink.close()
        raise
    return opened


__all__ = ["SINKS", "OutputSpec", "Sink", "SinkOptions", "factory", "open_sinks"]
