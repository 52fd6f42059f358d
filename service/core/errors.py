"""The single exception root of bdsfix, its few subclasses, and the process exit codes.

Each error class carries the exit code the ``bdsfix`` command returns for it (the table
below, also in the README's "Exit codes" section). The CLI prints one line
``bdsfix COMMAND: error: MESSAGE`` on stderr and exits with that code, never a traceback.
"""

EXIT_OK = 0
"""Success (also a clean stop on SIGTERM)."""
EXIT_INTERNAL = 1
"""An unexpected internal error (a bug); ``-v`` shows the traceback."""
EXIT_USAGE = 2
"""Bad arguments or configuration: flags, config file (missing, unreadable, bad TOML,
unknown keys, wrong types or values). argparse uses 2 for usage errors too."""
EXIT_INPUT = 3
"""An input or output that cannot be used: a missing or unopenable receiver device or
capture file, an unreadable or malformed nav/obs file, an output file that cannot be written."""
EXIT_BIND = 4
"""A listening socket cannot be bound: NMEA TCP port or ZeroMQ endpoint already in use,
address not available, or permission denied."""
EXIT_REFUSED = 5
"""A receiver refused part of the set-up asked of it (UBX ACK-NAK to a CFG message): it is
left as its answers say (the settings it acknowledged are in effect, nothing is saved)."""
EXIT_INTERRUPTED = 130
"""Interrupted by SIGINT (Ctrl-C) outside the daemon loop."""


class BdsfixError(Exception):
    """Root of every error bdsfix raises on purpose."""

    exit_code: int = EXIT_USAGE


class FramingError(BdsfixError):
    """Bytes or lines that do not form a valid frame or record (names file/offset/line)."""

    exit_code = EXIT_INPUT


class DecodeError(BdsfixError):
    """A frame that is well formed but whose content cannot be interpreted."""

    exit_code = EXIT_INPUT


class EphemerisError(BdsfixError):
    """No usable ephemeris, or an ephemeris that is stale or unhealthy."""

    exit_code = EXIT_INPUT


class ConfigError(BdsfixError):
    """A bad configuration file, key or command-line value."""

    exit_code = EXIT_USAGE


class InputError(BdsfixError):
    """A device or file that cannot be opened, read or written."""

    exit_code = EXIT_INPUT


class BindError(ConfigError):
    """A listening address that cannot be bound (in use, not local, not permitted)."""

    exit_code = EXIT_BIND


class ReceiverSilentError(InputError):
    """A receiver that does not answer a configuration message (no ACK/NAK in time): not a
    u-blox receiver, a wrong baud rate, or its UBX input is off (exit 3, as a device that
    cannot be used)."""


class ReceiverRefusedError(BdsfixError):
    """A receiver that answered ACK-NAK to part of its set-up (exit 5)."""

    exit_code = EXIT_REFUSED
