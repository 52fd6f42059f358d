"""Tiny capture files made in tests."""

from __future__ import annotations

from pathlib import Path

from drivers.ubx import fletcher8


def ubx_poll_capture(path: Path) -> Path:
    """A capture of one valid UBX frame (a NAV-PVT poll, empty payload): readable and
    recognisable, so that checks after the source are reached."""
    body = b"\x01\x07\x00\x00"
    path.write_bytes(b"\xb5\x62" + body + fletcher8(body))
    return path
