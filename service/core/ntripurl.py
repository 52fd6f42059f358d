"""An NTRIP source named in ``nav``: ``ntrip://user:pass@host:port/MOUNT``, parsed and checked.

NTRIP (RTCM 10410.1, "Networked Transport of RTCM via Internet Protocol", v1 and v2) is HTTP
with Basic authentication: the client asks a caster for one mountpoint (``GET /MOUNT``) and
reads the RTCM 3 stream it relays. The daemon reads broadcast ephemerides from it (RTCM 1042).

The credentials are secrets: :meth:`NtripUrl.redacted` (also ``str()`` and ``repr()``) shows
neither user nor password, and every message of :func:`parse_ntrip_url` names the URL in
that form, so no log line or error carries them. :func:`redact` is the one function that
hides them in any other text that may be a URL, whatever its scheme (``ntrips://``,
``http://``, ``ntrip:user:pass@...`` without ``//``) and whatever the password holds (``@``,
``/``, a newline); :func:`looks_like_url` tells such a ``nav`` entry from a file name, so a
URL of another scheme is refused as a URL (redacted), never opened as a file.

A URL with a user and no password takes the password from ``$BDSFIX_NTRIP_PASSWORD`` (keeps
it out of the process list and the config). User and password may be percent-encoded
(``%40`` for ``@``, ``%3A`` for ``:``).
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


_SCHEME_HEAD = re.compile(r"[A-Za-z][A-Za-z0-9+.\-]*:/{1,2}")
"""A URL's ``scheme://`` (or ``scheme:/``, as a :class:`~pathlib.Path` folds ``//``)."""
_SCHEME = re.compile(r"[A-Za-z][A-Za-z0-9+.\-]*:")


def looks_like_url(text: str) -> bool:
    """Whether ``text`` is (or is meant as) a URL rather than a file name: a scheme followed
    by ``/`` (``ntrips://``, ``http://``, a Path-folded ``ntrip:/``), or a scheme and an
    ``@`` (``ntrip:alice:pw@host/M``, ``alice:pw@host/M``)."""
    t = text.strip()
    m = _SCHEME.match(t)
    return m is not None and (t[m.end() :].startswith("/") or "@" in t)


def redact(text: str) -> str:
    """``text`` with everything before its last ``@`` but a leading ``scheme://`` shown as
    ``***``: ``ntrips://u:p@h/M`` -> ``ntrips://***@h/M``, ``ntrip:u:p@h/M`` -> ``***@h/M``.

    Whatever the scheme, and whatever the user or the password hold (``@``, ``:``, ``/``, a
    newline), since a URL's host and path never hold ``@``. Text without ``@`` is returned
    as it is."""
    head, at, tail = text.rpartition("@")
    if not at:
        return text
    m = _SCHEME_HEAD.match(head)
    return f"{m.group(0) if m else ''}***@{tail}"


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
        m = _SCHEME_HEAD.match(raw)  # "ntrip:user:pw@" has no scheme to show: it is the user
        scheme = m.group(0).rstrip("/")[:-1][:20] if m else ""
        scheme = f" (scheme {scheme!r}: only ntrip:// is read)" if m else ""
        raise bad(f"not an NTRIP URL{scheme}")
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
