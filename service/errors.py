"""The single exception root of bdsfix and its few subclasses."""


class BdsfixError(Exception):
    """Root of every error bdsfix raises on purpose."""


class FramingError(BdsfixError):
    """Bytes or lines that do not form a valid frame or record (names file/offset/line)."""


class DecodeError(BdsfixError):
    """A frame that is well formed but whose content cannot be interpreted."""


class EphemerisError(BdsfixError):
    """No usable ephemeris, or an ephemeris that is stale or unhealthy."""


class ConfigError(BdsfixError):
    """A bad configuration file, key or command-line value."""
