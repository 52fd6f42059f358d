"""NMEA 0183 sentences for a fix, built with pynmeagps (output sentences, msgmode GET).

GGA, RMC, GSA, GSV (NMEA 4.11: signal ID field, BDS B1I = 1; GSA system ID 4 = BeiDou), GST
and ZDA once time is known. The talker of GGA/RMC/GSA/GST/ZDA is configurable (GN by default,
GB, BD or GP); GSV names its constellation, so it uses GB (BD when BD was asked for).
Latitude and longitude carry 7 decimals of minutes (pynmeagps high-precision mode, 0.2 mm),
times keep hundredths of a second for 10 Hz output. A fix with ``mode == "none"`` gives a GGA
with quality 0 and RMC status V, as receivers do before they have a position.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence

from pynmeagps import GET, NMEAMessage

from service.constants import prn_number
from service.types import Fix, SatView

TALKERS = ("GN", "GB", "BD", "GP")
BDS_SYSTEM_ID = "4"
B1I_SIGNAL_ID = "1"


def _msg(talker: str, msg_id: str, **fields: object) -> bytes:
    return bytes(NMEAMessage(talker, msg_id, GET, hpnmeamode=True, **fields).serialize())


def _hemis(lat: float, lon: float) -> tuple[float, str, float, str]:
    return abs(lat), "N" if lat >= 0 else "S", abs(lon), "E" if lon >= 0 else "W"


def _time(utc: dt.datetime) -> dt.time:
    # hundredths of a second, as NMEA carries them
    cs = round(utc.microsecond / 10_000)
    base = utc.replace(microsecond=0) + dt.timedelta(milliseconds=10 * cs)
    return base.time()


def _gsv(sky: Sequence[SatView], talker: str) -> list[bytes]:
    sats = sorted(sky, key=lambda s: prn_number(s.prn))
    n_msg = max(1, math.ceil(len(sats) / 4))
    out = []
    for k in range(n_msg):
        fields: dict[str, object] = {"numMsg": n_msg, "msgNum": k + 1, "numSV": len(sats)}
        for j, s in enumerate(sats[4 * k : 4 * k + 4], start=1):
            fields[f"svid_{j:02d}"] = prn_number(s.prn)
            fields[f"elv_{j:02d}"] = round(s.el_deg)
            fields[f"az_{j:02d}"] = round(s.az_deg) % 360
            fields[f"cno_{j:02d}"] = round(s.cn0_dbhz) if math.isfinite(s.cn0_dbhz) else ""
        fields["signalID"] = B1I_SIGNAL_ID
        out.append(_msg(talker, "GSV", **fields))
    return out


def sentences_for_fix(
    fix: Fix, *, utc: dt.datetime, talker: str = "GN", time_known: bool = True
) -> list[bytes]:
    """Sentences for one epoch's fix, in the order GGA, RMC, GSA, GSV, GST, ZDA."""
    if talker not in TALKERS:
        raise ValueError(f"NMEA talker must be one of {', '.join(TALKERS)}, got {talker!r}")
    t = _time(utc)
    has_fix = fix.ok and None not in (fix.lat_deg, fix.lon_deg, fix.alt_m)
    pos: dict[str, object] = {"lat": "", "NS": "", "lon": "", "EW": ""}
    hdop: object = ""
    if has_fix:
        lat, ns, lon, ew = _hemis(float(fix.lat_deg or 0.0), float(fix.lon_deg or 0.0))
        pos = {"lat": lat, "NS": ns, "lon": lon, "EW": ew}
        hdop = round(fix.hdop, 2) if fix.hdop is not None else ""
    out = [
        _msg(
            talker,
            "GGA",
            time=t,
            **pos,
            quality=1 if has_fix else 0,
            numSV=len(fix.used),
            HDOP=hdop,
            alt=round(float(fix.alt_m or 0.0), 3) if has_fix else "",
            altUnit="M",
            sep=0.0 if has_fix else "",
            sepUnit="M",
            diffAge="",
            diffStation="",
        ),
        _msg(
            talker,
            "RMC",
            time=t,
            status="A" if has_fix else "V",
            **pos,
            spd="",
            cog="",
            date=utc.date(),
            mv="",
            mvEW="",
            posMode="A" if has_fix else "N",
            navStatus="V",
        ),
    ]
    if not has_fix:
        return out
    gsa: dict[str, object] = {"opMode": "A", "navMode": 3}
    used = sorted(fix.used, key=prn_number)[:12]
    for j in range(12):
        gsa[f"svid_{j + 1:02d}"] = prn_number(used[j]) if j < len(used) else ""
    gsa |= {
        "PDOP": round(fix.pdop, 2) if fix.pdop is not None else "",
        "HDOP": hdop,
        "VDOP": round(fix.vdop, 2) if fix.vdop is not None else "",
        "systemId": BDS_SYSTEM_ID,
    }
    out.append(_msg(talker, "GSA", **gsa))
    if fix.sky:
        out.extend(_gsv(fix.sky, "BD" if talker == "BD" else "GB"))
    if fix.std_enu_m is not None:
        se, sn, su = fix.std_enu_m
        out.append(
            _msg(
                talker,
                "GST",
                time=t,
                rangeRms=round(fix.resid_rms_m or 0.0, 3),
                stdMajor=round(max(se, sn), 3),
                stdMinor=round(min(se, sn), 3),
                orient=0.0 if sn >= se else 90.0,
                stdLat=round(sn, 3),
                stdLong=round(se, 3),
                stdAlt=round(su, 3),
            )
        )
    if time_known:
        out.append(
            _msg(
                talker,
                "ZDA",
                time=t,
                day=utc.day,
                month=utc.month,
                year=utc.year,
                ltzh="00",
                ltzn="00",
            )
        )
    return out
