"""One daemon per state directory: an exclusive ``flock`` on a lock file in it.

Two daemons sharing a state directory each keep an ephemeris store in memory and save it
over the other's (the last writer wins: 9 of 14 sets were lost in the probe of issue 23).
:func:`lock_state_dir` takes ``flock(LOCK_EX | LOCK_NB)`` on :data:`LOCK_NAME` in the
directory and holds it for the life of the process (the kernel releases it when the process
ends, however it ends, so a crash leaves no stale lock); the file holds the holder's pid,
for the message a second daemon gets: one line, exit 3 (:class:`InputError`).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from service.core.errors import InputError

LOCK_NAME = "bdsfix.lock"
_HELD: dict[Path, int] = {}  # lock file -> descriptor, held until the process ends


def lock_state_dir(state_dir: Path) -> Path:
    """Take the state directory's lock (once per process); InputError naming the holder if
    another process has it. Returns the lock file's path."""
    path = (state_dir / LOCK_NAME).resolve()
    if path in _HELD:
        return path
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o600)
    except OSError as exc:
        raise InputError(
            f"state directory {state_dir}: cannot open {path}: {exc.strerror}"
        ) from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode("ascii", "replace").strip()
        os.close(fd)
        pid = f"pid {holder}" if holder.isdigit() else "a process"
        raise InputError(
            f"state directory {state_dir} is in use by another bdsfix ({pid} holds {path}): "
            "one daemon per state directory (give this one --state-dir)"
        ) from None
    except OSError as exc:
        os.close(fd)
        raise InputError(
            f"state directory {state_dir}: cannot lock {path}: {exc.strerror}"
        ) from exc
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode("ascii"))
    _HELD[path] = fd
    return path
