"""NMEA 0183 sentences for a fix (output sentences, as pynmeagps builds them in msgmode GET).

Sentences, in order: RMC, VTG, GGA, GSA, GSV, GST, ZDA (the u-blox order). gpsd (3.22)
reports a fix at the end of each sentence that it has learnt ends a cycle, and fills a
missing speed with the distance from the previous fix over the time step: with GGA first
it reported a second fix per epoch after GGA, with a speed of tens of m/s from a static
receiver's position noise. With RMC and VTG first every report carries our speed
(tests/system/test_service_io.py).

- Serialisation: the field values are chosen here (the pynmeagps keyword names and types of
  NMEA 0183 / NMEA 4.11 GGA, RMC, VTG, GSA, GSV, GST and ZDA) and written by
  :func:`plain_sentence`, a hand-written formatter: comma-joined fields, ``*`` and the XOR
  checksum of NMEA 0183. It exists for its cost: pynmeagps' ``NMEAMessage`` took ~0.1 ms
  per sentence, ~8 sentences per 10 Hz epoch, 41 % of ``bdsfix replay --max-speed``'s
  stream loop (bench/bench_replay.py --profile); with the plain formatter an epoch's
  sentences take ~60 us, the choice of their field values included. It is cross-checked
  against :func:`pynmeagps_sentence` (pynmeagps' ``NMEAMessage`` with ``hpnmeamode``, the
  independent reference) byte for byte, for every fix of the golden captures and for
  generated fixes (tests/output/test_nmea_plain.py), and each of its sentences parses back
  with pynmeagps' ``NMEAReader``.

- Talker: GGA/RMC/GST/ZDA use the configured talker (``GN`` by default, ``GB``, ``BD`` or
  ``GP``). GSA and GSV list BeiDou satellites only, so they use BeiDou's ``GB`` (``BD`` when
  ``BD`` was asked for) unless ``gsa_talker`` names GSA's: gpsd 3.22 (Debian 12) takes the
  constellation of GSA satellite IDs from the talker alone (``processGSA`` in
  driver_nmea0183.c reads the system-ID field but does not use it), so it read the PRNs of
  a ``GNGSA`` as GPS and matched none of the BeiDou satellites of the ``GBGSV``: its SKY had
  ``uSat`` 0 and every satellite ``used: false`` (issue 23). ``GBGSA`` maps IDs to BeiDou
  in gpsd 3.22 and later, and later gpsd also reads the system ID of a ``GNGSA``. One
  limit remains in gpsd 3.22: it takes the constellation of a GSV from the talker only in
  the first sentence of a group, so a BeiDou ID 33-63 in the second or later GSV is filed
  as SBAS there and not marked used.
- NMEA 4.11 fields: GSA ends with the GNSS system ID, 4 = BeiDou; GSV ends with the signal
  ID, 1 = B1I (D1 and D2 alike, as u-blox NMEA 4.11 output and gpsd's tables have it).
  Satellite IDs are BDS PRNs 1-63.
- Several systems (issue 19, :data:`OTHER_SYSTEMS`): one GSA per system with used
  satellites, then one GSV group per system in view, each under its system's talker (GP
  GPS, system ID 1, signal 1 L1 C/A; GA Galileo, system ID 3, signal 7 E1; BeiDou's as
  above), GPS first (:data:`_NMEA_ORDER`); IDs are each system's PRNs. A BeiDou-only fix
  gives exactly the sentences it always did.
- Precision: latitude/longitude carry 7 decimals of minutes (pynmeagps ``hpnmeamode``:
  1e-7 min = 0.19 mm); times carry hundredths of a second (hhmmss.ss), so 10 Hz output
  keeps distinct stamps; the altitude carries millimetres.
- Length: NMEA 0183 caps a sentence at 82 characters including ``$`` and CRLF. GGA is 80
  for typical values; when the altitude has five digits or HDOP reaches 10 it is rebuilt
  with centimetre altitude and then 0.1 HDOP; latitude/longitude precision is never cut,
  so in extreme cases GGA may still exceed 82 (gpsd accepts longer sentences). GST
  values switch from millimetres to decimetres at 100 m and to metres at 10 km.
- GST: 1-sigma figures of the solution covariance (G^T W G)^-1 of the error model
  (:func:`service.engine.solver.measurement_sigma_m`): the horizontal error ellipse (semi-axes
  and the major axis' orientation from true north) and the latitude, longitude and
  altitude standard deviations; ``rangeRms`` is the RMS of the post-fit residuals.
- Altitude: GGA carries the ellipsoidal height as altitude with geoid separation 0.0, so
  altitude + separation is the height above the CGCS2000 ellipsoid as gpsd computes it.
- Fix quality: fast and SPP fixes are both GGA quality 1 (autonomous) with GSA mode 3, so
  gpsd reports a 3D fix. A fix with ``mode == "none"`` gives only RMC with status V and GGA
  with quality 0 and an empty position (gpsd: no fix); pynmeagps fills the hemisphere
  fields with N/E even then. Its time is the receiver's unsolved tag, so no ZDA follows;
  while no GPS week is known (``no_time``) the time and date fields are empty.
- Speed and course (:mod:`service.engine.velocity`): RMC's speed over ground in knots
  (1 kn = 1852 m / 3600 s) and course over ground in degrees from true north; VTG follows
  RMC with the same course (true; the magnetic course is left empty), speed in knots and
  km/h and mode A. Both only for a fix with a velocity (else RMC's fields are empty and
  there is no VTG); the course only while its 1-sigma is at most
  :data:`COURSE_MAX_STD_DEG` (a static receiver's course is noise). Speed carries
  0.001 kn / 0.001 km/h, course 0.01 deg.
- ZDA only with ``time_known`` (the caller knows UTC, e.g. after a first fix); day and month
  are two digits (``$GNZDA,hhmmss.ss,dd,mm,yyyy,00,00``, NMEA 0183 field format ``xx``).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Sequence
from functools import reduce
from operator import xor

from pynmeagps import GET, NMEAMessage

from service.core.constants import C_M_S
from service.core.systems import prn_number
from service.core.timebase import gpst_in_leap_second, utc_from_gpst
from service.core.types import UNKNOWN_WEEK, Fix, SatView

TALKERS = ("GN", "GB", "BD", "GP")
BDS_SYSTEM_ID = "4"
B1I_SIGNAL_ID = "1"
OTHER_SYSTEMS: dict[str, tuple[str, str, str]] = {
    "G": ("GP", "1", "1"),  # GPS: talker GP, system ID 1, signal ID 1 (L1 C/A)
    "E": ("GA", "3", "7"),  # Galileo: talker GA, system ID 3, signal ID 7 (E1-C/E1-B)
}
"""NMEA 4.11 talker, GNSS system ID (GSA) and signal ID (GSV) of the other systems' rows."""
_NMEA_ORDER = ("G", "C", "E")
"""Order of the systems' GSA and GSV groups: GPS first, since gpsd (3.22 and later) starts a
new sky at a GPGSV group of the L1 C/A signal and adds the other talkers' groups after it
(``processGSV`` in driver_nmea0183.c)."""
NMEA_MAX_LEN = 82
GSA_MAX_SV = 12
GSV_SATS_PER_SENTENCE = 4
KNOTS_PER_M_S = 3600.0 / 1852.0
KMH_PER_M_S = 3.6
COURSE_MAX_STD_DEG = 10.0
"""Course over ground is reported only while its 1-sigma [deg] is at most this."""


_LAT, _LON, _NS, _EW, _TIME, _DATE, _HEX, _DEC, _INT, _CHAR = (
    "LA", "LN", "LAD", "LND", "TM", "DT", "HX", "DE", "IN", "CH"
)  # fmt: skip
_NOMINAL = {_HEX: "0", _DEC: "0.0", _INT: "0", _CHAR: "", _LAT: "", _LON: "", _NS: "N", _EW: "E"}
"""The text pynmeagps writes for a field that is not given (``NMEAMessage.nomval``)."""


def _gsv_keys(j: int) -> tuple[str, str, str, str]:
    """Names of GSV's j-th satellite group (pynmeagps: svid, elv, az, cno, integers)."""
    return (f"svid_{j:02d}", f"elv_{j:02d}", f"az_{j:02d}", f"cno_{j:02d}")


_GSV_KEYS = tuple(_gsv_keys(j) for j in range(1, GSV_SATS_PER_SENTENCE + 1))
_FIELDS: dict[str, tuple[tuple[str, str], ...]] = {
    # pynmeagps' GET payload definitions (nmeatypes_get) of the sentences written here
    "GGA": (
        ("time", _TIME), ("lat", _LAT), ("NS", _NS), ("lon", _LON), ("EW", _EW),
        ("quality", _INT), ("numSV", _INT), ("HDOP", _DEC), ("alt", _DEC), ("altUnit", _CHAR),
        ("sep", _DEC), ("sepUnit", _CHAR), ("diffAge", _DEC), ("diffStation", _INT),
    ),
    "RMC": (
        ("time", _TIME), ("status", _CHAR), ("lat", _LAT), ("NS", _NS), ("lon", _LON),
        ("EW", _EW), ("spd", _DEC), ("cog", _DEC), ("date", _DATE), ("mv", _DEC),
        ("mvEW", _CHAR), ("posMode", _CHAR), ("navStatus", _CHAR),
    ),
    "VTG": (
        ("cogt", _DEC), ("cogtUnit", _CHAR), ("cogm", _DEC), ("cogmUnit", _CHAR),
        ("sogn", _DEC), ("sognUnit", _CHAR), ("sogk", _DEC), ("sogkUnit", _CHAR),
        ("posMode", _CHAR),
    ),
    "GSA": (
        ("opMode", _CHAR), ("navMode", _INT),
        *((f"svid_{j:02d}", _INT) for j in range(1, GSA_MAX_SV + 1)),
        ("PDOP", _DEC), ("HDOP", _DEC), ("VDOP", _DEC), ("systemId", _HEX),
    ),
    "GSV": (("numMsg", _INT), ("msgNum", _INT), ("numSV", _INT)),  # then groups, signalID
    "GST": (
        ("time", _TIME), ("rangeRms", _DEC), ("stdMajor", _DEC), ("stdMinor", _DEC),
        ("orient", _DEC), ("stdLat", _DEC), ("stdLong", _DEC), ("stdAlt", _DEC),
    ),
    "ZDA": (
        ("time", _TIME), ("day", _INT), ("month", _INT), ("year", _INT), ("ltzh", _CHAR),
        ("ltzn", _CHAR),
    ),
}  # fmt: skip


def _dmm(deg: object, width: int) -> str:
    """|deg| as (d)ddmm.mmmmmmm, zero-filled to ``width`` (pynmeagps ``ddd2dmm``, hpmode);
    empty for a value that is not a number."""
    if not isinstance(deg, (int, float)):
        return ""
    whole, minutes = divmod(abs(deg) * 60, 60)
    return f"{int(whole * 100) + minutes:.7f}".zfill(width)


def _lat_text(value: object, fields: dict[str, object]) -> str:
    return _dmm(value, 12)


def _lon_text(value: object, fields: dict[str, object]) -> str:
    return _dmm(value, 13)


def _ns_text(value: object, fields: dict[str, object]) -> str:
    lat = fields.get("lat")
    return "S" if isinstance(lat, (int, float)) and lat < 0 else "N"


def _ew_text(value: object, fields: dict[str, object]) -> str:
    lon = fields.get("lon")
    return "W" if isinstance(lon, (int, float)) and lon < 0 else "E"


def _time_text(value: object, fields: dict[str, object]) -> str:
    if isinstance(value, str):
        return value.replace(":", "")
    t: dt.time = value  # type: ignore[assignment]
    return f"{t.hour:02d}{t.minute:02d}{t.second:02d}.{t.microsecond // 10_000:02d}"


def _date_text(value: object, fields: dict[str, object]) -> str:
    if isinstance(value, str):
        v = value.replace("-", "")
        return f"{v[6:8]}{v[4:6]}{v[2:4]}"
    d: dt.date = value  # type: ignore[assignment]
    return f"{d.day:02d}{d.month:02d}{d.year % 100:02d}"


_Writer = Callable[[object, dict[str, object]], str]
_WRITERS: dict[str, _Writer] = {
    _LAT: _lat_text,
    _LON: _lon_text,
    _NS: _ns_text,
    _EW: _ew_text,
    _TIME: _time_text,
    _DATE: _date_text,
}
"""How pynmeagps' ``NMEAMessage.val2str`` writes a field of each kind other than those it
writes with ``str()`` (:data:`_PLAIN_KINDS`): ``(value, all fields) -> text``."""


_PLAIN_KINDS = frozenset({_HEX, _DEC, _INT, _CHAR})
"""Kinds pynmeagps writes with ``str()``."""
_SPECS: dict[str, tuple[tuple[str, _Writer | None, str | None], ...]] = {
    msg_id: tuple(
        (name, None if kind in _PLAIN_KINDS else _WRITERS[kind], _NOMINAL.get(kind))
        for name, kind in spec
    )
    for msg_id, spec in _FIELDS.items()
}
"""``_FIELDS`` as (name, writer or None for ``str()``, text when not given) for the
formatter."""


def plain_sentence(talker: str, msg_id: str, fields: dict[str, object]) -> bytes:
    """``$`` talker msg_id ``,`` fields ``*`` checksum CRLF (NMEA 0183: the checksum is
    the XOR of the characters between ``$`` and ``*``, two hex digits), for the sentences of
    this module: the bytes pynmeagps' ``NMEAMessage(talker, msg_id, GET, hpnmeamode=True,
    **fields).serialize()`` gives (:func:`pynmeagps_sentence`), at a few percent of its cost.
    Fields not given get pynmeagps' nominal text (times and dates must be given)."""
    parts = [talker + msg_id]
    get = fields.get
    for name, writer, nominal in _SPECS[msg_id]:
        value = get(name, nominal)
        if writer is None:
            parts.append(str(value))
        elif value is None:
            raise KeyError(f"{msg_id} needs its {name} field")
        else:
            parts.append(writer(value, fields))
    if msg_id == "GSV":
        # pynmeagps' group count for generated messages: the largest _NN suffix given
        n_groups = max([int(k.split("_", 1)[1]) for k in fields if "_" in k], default=0)
        for j in range(1, n_groups + 1):
            keys = _GSV_KEYS[j - 1] if j <= len(_GSV_KEYS) else _gsv_keys(j)
            parts.extend([str(get(key, 0)) for key in keys])
        parts.append(str(get("signalID", "0")))
    return _framed(",".join(parts))


def _framed(text: str) -> bytes:
    """``$`` text ``*`` checksum CRLF (NMEA 0183: the XOR of the characters between ``$``
    and ``*``, two hex digits)."""
    data = text.encode()
    return b"$" + data + b"*%02X\r\n" % reduce(xor, data, 0)


def _plain_lead(
    talker: str,
    t: dt.time | str,
    when: dt.datetime,
    has_fix: bool,
    pos: dict[str, object],
    speed: tuple[object, object, object],
    fix: Fix,
) -> list[bytes]:
    """RMC, VTG (with a speed) and GGA of :func:`lead_sentences`'s field values, as
    :func:`plain_sentence` writes them, each field's text made once (the time and the
    position serve RMC and GGA) and no field dict: these are the sentences between an
    epoch's solve and its GGA on the socket. The same bytes as :func:`plain_sentence`
    (compared with pynmeagps' by tests/output/test_nmea_plain.py and with the goldens)."""
    time_text = _time_text(t, {})
    lat, lon = pos["lat"], pos["lon"]
    south = isinstance(lat, (int, float)) and lat < 0
    west = isinstance(lon, (int, float)) and lon < 0
    where = f"{_dmm(lat, 12)},{'S' if south else 'N'},{_dmm(lon, 13)},{'W' if west else 'E'}"
    knots, kmh, course = speed
    mode = "A" if has_fix else "N"
    out = [
        _framed(
            f"{talker}RMC,{time_text},{'A' if has_fix else 'V'},{where},{knots!s},"
            f"{course!s},{_date_text(when.date(), {})},,,{mode},V"
        )
    ]
    if knots != "":
        out.append(_framed(f"{talker}VTG,{course!s},T,,M,{knots!s},N,{kmh!s},K,A"))
    head = f"{talker}GGA,{time_text},{where},"
    if not has_fix:
        out.append(_framed(f"{head}0,{len(fix.used)},,,M,,M,,"))
        return out
    alt_m = float(fix.alt_m)  # type: ignore[arg-type]
    sentence = b""
    for alt_nd, hdop_nd in _GGA_FORMS:
        hdop, alt = _dop(fix.hdop, hdop_nd), round(alt_m, alt_nd)
        sentence = _framed(f"{head}1,{len(fix.used)},{hdop!s},{alt!s},M,0.0,M,,")
        if len(sentence) <= NMEA_MAX_LEN:
            break
    out.append(sentence)
    return out


def pynmeagps_sentence(talker: str, msg_id: str, fields: dict[str, object]) -> bytes:
    """The same sentence built by pynmeagps (``NMEAMessage``, GET, ``hpnmeamode``): the
    independent reference :func:`plain_sentence` is checked against."""
    return bytes(NMEAMessage(talker, msg_id, GET, hpnmeamode=True, **fields).serialize())


_serialize = plain_sentence
"""What writes the sentences (tests swap in :func:`pynmeagps_sentence` to compare)."""


def _msg(talker: str, msg_id: str, **fields: object) -> bytes:
    return _serialize(talker, msg_id, fields)


def _fix_gpst(fix: Fix) -> tuple[int, float] | None:
    """GPST (week, tow) of a fix: the receiver's time tag minus the solved clock bias for a
    published fix; a declined fix has no trusted clock, so its tag as is; None when the tag
    has no GPS week (``no_time``)."""
    if fix.gpst_week == UNKNOWN_WEEK:
        return None
    bias_s = (fix.clock_bias_m or 0.0) / C_M_S if fix.ok else 0.0
    return fix.gpst_week, fix.gpst_tow_s - bias_s


def fix_utc(fix: Fix) -> dt.datetime | None:
    """The time NMEA gives a fix (naive UTC) from its GPST (:func:`_fix_gpst`); None when
    the tag has no GPS week, so no date either."""
    g = _fix_gpst(fix)
    return None if g is None else utc_from_gpst(*g)


def _clock(fix: Fix, utc: dt.datetime) -> tuple[dt.datetime, dt.time | str]:
    """The date and the hhmmss.ss field NMEA gives ``fix`` at ``utc``, to the hundredth.

    In an inserted leap second (UTC 23:59:60.xx, which a ``datetime`` cannot hold and
    :func:`utc_from_gpst` gives as a repeated 23:59:59.xx) the field reads ``235960.xx``, as
    NMEA 0183 allows seconds up to 60 (time field format hhmmss.ss)."""
    when = nmea_time(utc)
    g = _fix_gpst(fix)
    if g is not None:
        week, tow_s = g
        tow_cs = round(tow_s * 100.0) / 100.0
        if gpst_in_leap_second(week, tow_cs):
            u = utc_from_gpst(week, tow_cs)
            cs = min(round(u.microsecond / 10_000), 99)
            return u.replace(microsecond=0), f"{u.hour:02d}:{u.minute:02d}:60.{cs:02d}"
    return when, when.time()


def nmea_time(utc: dt.datetime) -> dt.datetime:
    """``utc`` rounded to the hundredth of a second NMEA carries (date included)."""
    cs = round(utc.microsecond / 10_000)
    return utc.replace(microsecond=0) + dt.timedelta(milliseconds=10 * cs)


def _deg_for_dmm(deg: float) -> float:
    """``deg`` nudged so that pynmeagps' ddmm.mmmmmmm never shows 60.0000000 minutes.

    pynmeagps splits |deg|*60 with divmod and formats the minutes to 7 decimals; minutes
    that round up to 60 are returned as the next whole degree, which is exact in floats.
    """
    whole, minutes = divmod(abs(deg) * 60.0, 60.0)
    if round(minutes, 7) >= 60.0:
        return math.copysign(whole + 1.0, deg)
    return deg


def _dop(value: float | None, ndigits: int = 2) -> object:
    return round(value, ndigits) if value is not None and math.isfinite(value) else ""


def _metres(value: float) -> float | int:
    """A GST standard deviation with mm, dm or m resolution by size (keeps GST short)."""
    if not math.isfinite(value):
        return 0.0
    if abs(value) < 100.0:
        return round(value, 3)
    if abs(value) < 10_000.0:
        return round(value, 1)
    return round(value)


def _error_ellipse(fix: Fix) -> tuple[float, float, float]:
    """1-sigma semi-major and semi-minor axes [m] of the horizontal error ellipse and the
    major axis' orientation [deg from true north, 0-180), from the solution's east-north
    covariance; without one, axes along north and east from ``std_enu_m``."""
    se, sn, _ = fix.std_enu_m  # type: ignore[misc]
    if fix.cov_enu_m2 is None:
        return max(se, sn), min(se, sn), 0.0 if sn >= se else 90.0
    ee, en, nn = fix.cov_enu_m2[0][0], fix.cov_enu_m2[0][1], fix.cov_enu_m2[1][1]
    mean, half = (ee + nn) / 2.0, math.hypot((nn - ee) / 2.0, en)
    # the variance along azimuth t is ee sin^2 t + nn cos^2 t + 2 en sin t cos t: largest at
    # tan 2t = 2 en / (nn - ee)
    orient = math.degrees(0.5 * math.atan2(2.0 * en, nn - ee)) % 180.0
    major = math.sqrt(max(mean + half, 0.0))
    minor = math.sqrt(max(mean - half, 0.0))
    return major, minor, round(orient, 1) % 180.0


def _speed_course(fix: Fix) -> tuple[object, object, object]:
    """Speed over ground [kn], [km/h] and course [deg] for RMC/VTG ("" when unknown)."""
    vel = fix.velocity
    if vel is None or not math.isfinite(vel.speed_m_s):
        return "", "", ""
    course: object = ""
    if math.isfinite(vel.course_deg) and vel.std_course_deg <= COURSE_MAX_STD_DEG:
        course = round(vel.course_deg, 2) % 360.0
    return (
        round(vel.speed_m_s * KNOTS_PER_M_S, 3),
        round(vel.speed_m_s * KMH_PER_M_S, 3),
        course,
    )


def _int_or_empty(value: float) -> object:
    return round(value) if math.isfinite(value) else ""


def _prn_of(sat: SatView) -> int:
    return prn_number(sat.prn)


def gsv_sentences(
    sky: Sequence[SatView], talker: str = "GB", signal_id: str = B1I_SIGNAL_ID
) -> list[bytes]:
    """GSV sentences (4 satellites each, sorted by PRN) with the signal ID (B1I's unless
    given)."""
    sats = sorted(sky, key=_prn_of)
    n_sv = len(sats)
    n_msg = max(1, math.ceil(n_sv / GSV_SATS_PER_SENTENCE))
    if _serialize is plain_sentence:
        return _plain_gsv(sats, n_msg, talker, signal_id)
    out = []
    for k in range(n_msg):
        fields: dict[str, object] = {"numMsg": n_msg, "msgNum": k + 1, "numSV": n_sv}
        group = sats[GSV_SATS_PER_SENTENCE * k : GSV_SATS_PER_SENTENCE * (k + 1)]
        for (svid, elv, azk, cno), s in zip(_GSV_KEYS, group, strict=False):
            fields[svid] = prn_number(s.prn)
            fields[elv] = _int_or_empty(s.el_deg)
            az = _int_or_empty(s.az_deg)
            fields[azk] = az % 360 if isinstance(az, int) else az
            fields[cno] = _int_or_empty(s.cn0_dbhz)
        fields["signalID"] = signal_id
        out.append(_serialize(talker, "GSV", fields))
    return out


def _plain_gsv(sats: list[SatView], n_msg: int, talker: str, signal_id: str) -> list[bytes]:
    """:func:`gsv_sentences` of satellites ``sats`` (sorted) as :func:`plain_sentence`
    writes them from its fields: each satellite's four integer fields written once, each
    sentence joined from them (the text of the fields dictionary, without building it)."""
    groups = []
    for s in sats:
        az = _int_or_empty(s.az_deg)
        az = az % 360 if isinstance(az, int) else az
        el, cno = _int_or_empty(s.el_deg), _int_or_empty(s.cn0_dbhz)
        groups.append(f"{prn_number(s.prn)},{el},{az},{cno}")
    head, n_sv, tail = talker + "GSV", str(len(sats)), str(signal_id)
    n = GSV_SATS_PER_SENTENCE
    return [
        _framed(",".join([head, str(n_msg), str(k + 1), n_sv, *groups[n * k : n * (k + 1)], tail]))
        for k in range(n_msg)
    ]


_GGA_FORMS = ((3, 2), (2, 2), (2, 1))
"""GGA's (altitude, HDOP) decimals: millimetre altitude and 0.01 HDOP first; the shorter
forms only to stay within :data:`NMEA_MAX_LEN`."""


def _gga(
    talker: str, t: dt.time | str, fix: Fix, has_fix: bool, pos: dict[str, object] | None = None
) -> bytes:
    """GGA; ``pos``: the fix's ``lat``/``lon`` as RMC got them (:func:`_deg_for_dmm`)."""
    if not has_fix:
        return _msg(
            talker,
            "GGA",
            time=t,
            lat="",
            lon="",
            quality=0,
            numSV=len(fix.used),
            HDOP="",
            alt="",
            altUnit="M",
            sep="",
            sepUnit="M",
            diffAge="",
            diffStation="",
        )
    alt_m = float(fix.alt_m)  # type: ignore[arg-type]
    if pos is None:
        pos = {
            "lat": _deg_for_dmm(float(fix.lat_deg)),  # type: ignore[arg-type]
            "lon": _deg_for_dmm(float(fix.lon_deg)),  # type: ignore[arg-type]
        }
    sentence = b""
    for alt_nd, hdop_nd in _GGA_FORMS:
        sentence = _msg(
            talker,
            "GGA",
            time=t,
            **pos,
            quality=1,
            numSV=len(fix.used),
            HDOP=_dop(fix.hdop, hdop_nd),
            alt=round(alt_m, alt_nd),
            altUnit="M",
            sep=0.0,
            sepUnit="M",
            diffAge="",
            diffStation="",
        )
        if len(sentence) <= NMEA_MAX_LEN:
            break
    return sentence


def sentences_for_fix(
    fix: Fix,
    *,
    utc: dt.datetime | None,
    talker: str = "GN",
    time_known: bool = True,
    gsa_talker: str | None = None,
) -> list[bytes]:
    """Sentences for one epoch's fix, in the order RMC, VTG, GGA, GSA, GSV, GST, ZDA.

    ``utc`` is the fix's own time (naive UTC; None: unknown, for a declined fix only, gives
    empty time fields); ``time_known`` allows ZDA; ``gsa_talker``
    (default: BeiDou's, as GSV's) is GSA's talker. A publisher may send :func:`lead_sentences`
    first and :func:`sentences_after_gga` later: together they are this list.
    """
    return [
        *lead_sentences(fix, utc=utc, talker=talker, gsa_talker=gsa_talker),
        *sentences_after_gga(
            fix, utc=utc, talker=talker, time_known=time_known, gsa_talker=gsa_talker
        ),
    ]


def _check_talkers(talker: str, gsa_talker: str | None) -> None:
    for name in (talker, gsa_talker or talker):
        if name not in TALKERS:
            raise ValueError(f"NMEA talker must be one of {', '.join(TALKERS)}, got {name!r}")


def _rmc_void(talker: str) -> bytes:
    """RMC status V with empty time and date (no GPS week known yet)."""
    return _msg(
        talker,
        "RMC",
        time="",
        status="V",
        lat="",
        lon="",
        spd="",
        cog="",
        date="",
        mv="",
        mvEW="",
        posMode="N",
        navStatus="V",
    )


def _has_fix(fix: Fix) -> bool:
    return (
        fix.ok
        and fix.lat_deg is not None
        and fix.lon_deg is not None
        and fix.alt_m is not None
        and all(math.isfinite(v) for v in (fix.lat_deg, fix.lon_deg, fix.alt_m))
    )


def _checked(fix: Fix, utc: dt.datetime | None, talker: str, gsa_talker: str | None) -> bool:
    """Whether ``fix`` has a position to report, after checking the talkers and that a fix
    with a position comes with its time (ValueError otherwise)."""
    _check_talkers(talker, gsa_talker)
    has_fix = _has_fix(fix)
    if utc is None and has_fix:
        raise ValueError("a fix with a position needs its time")
    return has_fix


def lead_sentences(
    fix: Fix, *, utc: dt.datetime | None, talker: str = "GN", gsa_talker: str | None = None
) -> list[bytes]:
    """The first sentences of :func:`sentences_for_fix`: RMC, VTG (with a velocity) and GGA
    (quality 0 and no position without a fix), what a live sink gets first."""
    has_fix = _checked(fix, utc, talker, gsa_talker)
    if utc is None:
        return [_rmc_void(talker), _gga(talker, "", fix, False)]
    when, t = _clock(fix, utc)
    pos: dict[str, object] = {"lat": "", "lon": ""}
    if has_fix:
        # signed degrees: pynmeagps derives N/S and E/W from the sign
        pos = {
            "lat": _deg_for_dmm(float(fix.lat_deg)),  # type: ignore[arg-type]
            "lon": _deg_for_dmm(float(fix.lon_deg)),  # type: ignore[arg-type]
        }
    knots, kmh, course = speed = _speed_course(fix) if has_fix else ("", "", "")
    if _serialize is plain_sentence:  # (a test may swap in pynmeagps: the generic path then)
        return _plain_lead(talker, t, when, has_fix, pos, speed, fix)
    out = [
        _msg(
            talker,
            "RMC",
            time=t,
            status="A" if has_fix else "V",
            **pos,
            spd=knots,
            cog=course,
            date=when.date(),
            mv="",
            mvEW="",
            posMode="A" if has_fix else "N",
            navStatus="V",
        )
    ]
    if knots != "":
        out.append(
            _msg(
                talker,
                "VTG",
                cogt=course,
                cogtUnit="T",
                cogm="",
                cogmUnit="M",
                sogn=knots,
                sognUnit="N",
                sogk=kmh,
                sogkUnit="K",
                posMode="A",
            )
        )
    out.append(_gga(talker, t, fix, has_fix, pos))
    return out


def _gsa_fields(fix: Fix, used: Sequence[str], system_id: str) -> dict[str, object]:
    """GSA of one system: its used satellites (up to 12, by PRN), the fix's DOPs, its
    NMEA 4.11 system ID."""
    gsa: dict[str, object] = {"opMode": "A", "navMode": 3}
    ids = sorted(used, key=prn_number)[:GSA_MAX_SV]
    for j in range(GSA_MAX_SV):
        gsa[f"svid_{j + 1:02d}"] = prn_number(ids[j]) if j < len(ids) else ""
    return gsa | {
        "PDOP": _dop(fix.pdop),
        "HDOP": _dop(fix.hdop),
        "VDOP": _dop(fix.vdop),
        "systemId": system_id,
    }


def sentences_after_gga(
    fix: Fix,
    *,
    utc: dt.datetime | None,
    talker: str = "GN",
    time_known: bool = True,
    gsa_talker: str | None = None,
) -> list[bytes]:
    """The sentences of :func:`sentences_for_fix` that follow its GGA (none without a
    position)."""
    has_fix = _checked(fix, utc, talker, gsa_talker)
    if utc is None or not has_fix:
        return []
    when, t = _clock(fix, utc)
    out = []
    bds_talker = "BD" if talker == "BD" else "GB"
    systems = {p[:1] for p in fix.used} | {s.prn[:1] for s in fix.sky}
    order = [x for x in _NMEA_ORDER if x in systems or x == "C"]
    talkers = {**OTHER_SYSTEMS, "C": (bds_talker, BDS_SYSTEM_ID, B1I_SIGNAL_ID)}
    for letter in order:  # the GSAs, then the GSV groups, each system in _NMEA_ORDER
        mine = [p for p in fix.used if p[:1] == letter]
        if mine or letter == "C":
            gsa_as = (gsa_talker or bds_talker) if letter == "C" else talkers[letter][0]
            out.append(_msg(gsa_as, "GSA", **_gsa_fields(fix, mine, talkers[letter][1])))
    for letter in order:
        sky = [s for s in fix.sky if s.prn[:1] == letter]
        if sky:
            out.extend(gsv_sentences(sky, talkers[letter][0], talkers[letter][2]))
    if fix.std_enu_m is not None:
        se, sn, su = fix.std_enu_m
        major, minor, orient = _error_ellipse(fix)
        out.append(
            _msg(
                talker,
                "GST",
                time=t,
                rangeRms=_metres(fix.resid_rms_m or 0.0),
                stdMajor=_metres(major),
                stdMinor=_metres(minor),
                orient=orient,
                stdLat=_metres(sn),
                stdLong=_metres(se),
                stdAlt=_metres(su),
            )
        )
    if time_known:
        out.append(
            _msg(
                talker,
                "ZDA",
                time=t,
                day=f"{when.day:02d}",
                month=f"{when.month:02d}",
                year=when.year,
                ltzh="00",
                ltzn="00",
            )
        )
    return out
