"""An NTRIP source named in ``nav``: ``ntrip://user:pass@host:port/MOUNT``, parsed and checked.

NTRIP (RTCM 10410.1, "Networked Transport of RTCM via Internet Protocol", v1 and v2) is HTTP
with Basic authentication: the client asks a caster for one mountpoint (``GET /MOUNT``) and
reads the RTCM 3 stream it relays. The daemon reads broadcast ephemerides from it (RTCM 1042).

The credentials are secrets: :meth:`NtripUrl.redacted` (also ``str()`` and ``repr()``) shows
neither user nor password, and every message of :func:`parse_ntrip_url` names the URL in
that form, so no log line or error carries them. A URL with a user and no password takes the
password from ``$BDSFIX_NTRIP_PASSWORD`` (keeps it out of the process list and the config).
User and password may be percent-encoded (``%40`` for ``@``, ``%3A`` for ``:``).
"""

from __future__ import annotations

import base64
import os
import re
import urllib.parse
from dataclasses import dataclass, field

from service.core.errors import ConfigError

SCHEME = "ntrip://"
DEFAULT_PORT = 2101
"""The port IANA registered for NTRIP (``rtcm-sc104``)."""
PASSWORD_ENV = "BDSFIX_NTRIP_PASSWORD"  # noqa: S105 - the variable's name, not a password
EXAMPLE = "ntrip://user:pass@host:port/MOUNT"
_MOUNT = re.compile(r"[A-Za-z0-9._\-]{1,100}")
"""Mountpoint names as casters' source tables carry them (letters, digits, ``. _ -``)."""
_HOSTPORT = re.compile(
    r"(?:\[(?P<host6>[0-9A-Fa-f:.]{2,45})\]|(?P<host>[A-Za-z0-9.\-]{0,253}))(?::(?P<port>[^:]*))?"
)
"""A host name, IPv4 address or bracketed IPv6 address, then an optional ``:PORT``."""


def is_ntrip(text: str) -> bool:
    """Whether a ``nav`` entry names an NTRIP source (rather than a RINEX nav file)."""
    return text.strip().lower().startswith(SCHEME)


def redact(text: str) -> str:
    """``text`` with the ``user[:password]@`` of a URL (up to its last ``@``) as ``***@``."""
    return re.sub(r"(?<=//).*@", "***@", text)


@dataclass(frozen=True, slots=True)
class NtripUrl:
    """One caster mountpoint and the credentials to read it (never shown, see the module)."""

    host: str
    port: int
    mount: str
    user: str = field(default="", repr=False)
    password: str = field(default="", repr=False)

    def redacted(self) -> str:
        auth = "***@" if self.user else ""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{SCHEME}{auth}{host}:{self.port}/{self.mount}"

    def __str__(self) -> str:
        return self.redacted()

    def __repr__(self) -> str:
        return f"NtripUrl({self.redacted()!r})"

    def authorization(self) -> str | None:
        """The HTTP ``Authorization`` value (Basic, RFC 7617), None for an anonymous mount."""
        if not self.user:
            return None
        token = base64.b64encode(f"{self.user}:{self.password}".encode()).decode("ascii")
        return f"Basic {token}"


def parse_ntrip_url(text: str, env: dict[str, str] | None = None) -> NtripUrl:
    """Parse ``ntrip://[user[:password]@]host[:port]/MOUNT``; ConfigError (one line, no
    credentials in it) when it is not of that form."""
    environ = os.environ if env is None else env
    shown = redact(text.strip())

    def bad(why: str) -> ConfigError:
        return ConfigError(f"nav {shown!r}: {why}; expected {EXAMPLE}")

    raw = text.strip()
    if not is_ntrip(raw):
        raise bad("not an NTRIP URL")
    rest = raw[len(SCHEME) :]
    # A mountpoint never holds "@": the credentials end at the last one (a password may
    # hold "/", "@" or ":" unencoded), the host at the first "/" after it.
    userinfo, at, tail = rest.rpartition("@")
    if not at:
        userinfo, tail = "", rest
    hostport, slash, path = tail.partition("/")
    if not slash or not path:
        raise bad("no mountpoint")
    if "?" in path or "#" in path:
        raise bad("a mountpoint takes no query or fragment")
    mount = urllib.parse.unquote(path)
    if not _MOUNT.fullmatch(mount):
        raise bad(f"mountpoint {mount[:40]!r} is not a mountpoint name (A-Z a-z 0-9 . _ -)")
    user, colon, password = userinfo.partition(":")
    user = urllib.parse.unquote(user)
    password = urllib.parse.unquote(password)
    if at and not user:
        raise bad("an empty user name")
    if user and not colon:
        password = environ.get(PASSWORD_ENV, "")
    m = _HOSTPORT.fullmatch(hostport)
    if m is None:
        raise bad(f"{redact(hostport)[:60]!r} is not HOST[:PORT]")
    host, port_text = m.group("host6") or m.group("host"), m.group("port")
    if not host:
        raise bad("no host")
    port = DEFAULT_PORT
    if port_text is not None:
        if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise bad(f"port {port_text[:10]!r} is not in 1-65535")
        port = int(port_text)
    return NtripUrl(host=host, port=port, mount=mount, user=user, password=password)
