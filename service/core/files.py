"""Output files opened safely: never through a symlink, created with a fixed mode.

Every file bdsfix writes (JSONL, NMEA files, ``solve --out``, CSV, ``simulate --out``,
``coverage --json``) is opened here. The last path component is opened with
``O_NOFOLLOW``, so a symlink planted where an output goes (``/tmp/fixes.jsonl`` ->
``/etc/passwd``) is refused with :class:`~service.core.errors.InputError` instead of
truncating or appending to its target. A file that did not exist is created with
:data:`OUTPUT_MODE` whatever the umask; an existing file keeps its mode (an administrator
may have narrowed it). Devices and FIFOs (``/dev/null``) are opened as they are.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import IO, Any

from service.core.errors import InputError

PLOT_HINT = "--plot needs matplotlib: pip install '.[plot]' in the bdsfix checkout"
"""What ``--plot`` without matplotlib says (the ``plot`` extra of pyproject.toml): the
commands check it before computing, the plotting functions if called directly."""

OUTPUT_MODE = 0o644
"""Mode of a newly created output file (rw-r--r--), independent of the umask."""

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


def open_output_fd(path: str | Path, *, append: bool, mode: int = OUTPUT_MODE) -> int:
    """A write-only descriptor of ``path`` (appending, or truncated when ``append`` is
    False); InputError with one line naming the path when it is a symlink or cannot be
    opened."""
    flags = os.O_WRONLY | _NOFOLLOW | _CLOEXEC | (os.O_APPEND if append else os.O_TRUNC)
    for _ in range(8):  # the file may come and go between the two opens; try again
        try:
            fd = os.open(path, flags | os.O_CREAT | os.O_EXCL, mode)
        except FileExistsError:
            pass  # O_EXCL also refuses any symlink, dangling or not: the open below decides
        except OSError as exc:
            raise InputError(f"cannot write {path}: {exc.strerror}") from exc
        else:
            try:
                os.fchmod(fd, mode)  # we created it: exactly `mode`, whatever the umask
            except OSError:
                os.close(fd)
                raise
            return fd
        try:
            return os.open(path, flags)
        except FileNotFoundError:
            continue  # removed in between: create it
        except OSError as exc:
            if exc.errno == errno.ELOOP or os.path.islink(path):
                raise InputError(f"cannot write {path}: is a symlink (refused)") from exc
            raise InputError(f"cannot write {path}: {exc.strerror}") from exc
    raise InputError(f"cannot write {path}: it keeps appearing and disappearing")


def open_output(
    path: str | Path,
    *,
    append: bool = False,
    binary: bool = False,
    encoding: str = "utf-8",
    newline: str | None = None,
    buffering: int = -1,
) -> IO[Any]:
    """:func:`open_output_fd` as a file object (text unless ``binary``)."""
    fd = open_output_fd(path, append=append)
    try:
        if binary:
            return os.fdopen(fd, "ab" if append else "wb", buffering=buffering)
        return os.fdopen(
            fd, "a" if append else "w", buffering=buffering, encoding=encoding, newline=newline
        )
    except BaseException:
        os.close(fd)
        raise
