"""Streaming RINEX 3 readers (observation and navigation), versions 3.02-3.05.

Follows the RINEX 3.04/3.05 format description (IGS/RTCM-SC104):
- header labels in columns 61-80 (section 5.2, Table A2 / A14); ``SYS / # / OBS TYPES`` may
  continue on further lines, and the BDS B1I code is ``C1I`` in 3.02 and ``C2I`` from 3.03
  on (section 5.12, Table 10). Fields are indexed by the header's type list, so a leading
  Septentrio ``X1`` channel column is simply another type.
- observation epochs start with ``>`` (Table A3): flags 0/1 carry observations, 2-5 are
  followed by that many header/event lines, 6 by that many cycle-slip records. Each
  observation is 16 characters (F14.3 value, LLI, signal strength).
- BDS navigation records (Table A14) are 8 lines of four 19-character fields after the
  4-character indent; GLONASS and SBAS records are 4 lines; the toc epoch of a BDS record is
  BDT. Satellite IDs written with a space (``C 1``) are normalised to ``C01``.
A malformed file raises :class:`~service.errors.FramingError` naming the file and line.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from service.errors import FramingError
from service.timebase import BDT_GPST_OFFSET_S, gpst_from_datetime, normalize
from service.types import Ephemeris, KlobucharParams, MeasurementEpoch

log = logging.getLogger(__name__)

_NAV_LINES = {"G": 8, "E": 8, "J": 8, "C": 8, "I": 8, "R": 4, "S": 4}
_B1I_CODES = ("2I", "1I")  # 3.03+ name first, then the 3.02 one


def _sat_id(text: str) -> str:
    """``C 1``/``C01``/``C1`` -> ``C01``."""
    sys_char = text[0]
    num = text[1:].strip()
    return f"{sys_char}{int(num):02d}" if num.isdigit() else text.strip()


def _float(text: str) -> float:
    t = text.strip()
    return float(t.replace("D", "E").replace("d", "e")) if t else math.nan


def _epoch_datetime(fields: list[str]) -> dt.datetime:
    sec = float(fields[5])
    whole = int(sec)
    return dt.datetime(
        int(fields[0]), int(fields[1]), int(fields[2]), int(fields[3]), int(fields[4]), whole
    ) + dt.timedelta(microseconds=round((sec - whole) * 1e6))


@dataclass(frozen=True, slots=True)
class ObsHeader:
    """What a RINEX 3 observation header says."""

    version: float
    marker_name: str = ""
    receiver_type: str = ""
    approx_xyz_m: tuple[float, float, float] | None = None
    time_system: str = "GPS"
    obs_types: dict[str, tuple[str, ...]] = field(default_factory=dict)
    bds_code: str | None = None
    interval_s: float | None = None


def _read_header(fh: Iterator[str], path: Path, kind: str) -> tuple[dict[str, list[str]], int]:
    """Header lines grouped by label; returns (groups, line count)."""
    groups: dict[str, list[str]] = {}
    n = 0
    for line in fh:
        n += 1
        label = line[60:80].strip()
        if n == 1:
            if label != "RINEX VERSION / TYPE":
                raise FramingError(f"{path}:1: not a RINEX file (no RINEX VERSION / TYPE)")
            try:
                version = float(line[:9])
            except ValueError as exc:
                raise FramingError(f"{path}:1: bad RINEX version {line[:9]!r}") from exc
            if not 3.0 <= version < 4.0:
                raise FramingError(f"{path}:1: RINEX version {version} is not 3.xx")
            if line[20:21] != kind:
                raise FramingError(f"{path}:1: file type {line[20:21]!r}, expected {kind!r}")
        groups.setdefault(label, []).append(line.rstrip("\n"))
        if label == "END OF HEADER":
            return groups, n
    raise FramingError(f"{path}:{n}: no END OF HEADER")


class RinexObsReader:
    """Iterates the BDS B1I measurements of a RINEX 3 observation file, epoch by epoch."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with self.path.open("r", encoding="ascii", errors="replace") as fh:
                groups, self._header_lines = _read_header(fh, self.path, "O")
        except OSError as exc:
            raise FramingError(f"{self.path}: cannot read: {exc.strerror}") from exc
        self.header = self._parse_header(groups)

    def _parse_header(self, g: dict[str, list[str]]) -> ObsHeader:
        version = float(g["RINEX VERSION / TYPE"][0][:9])
        types: dict[str, list[str]] = {}
        current = ""
        for line in g.get("SYS / # / OBS TYPES", []):
            if line[0] != " ":
                current = line[0]
                types[current] = []
            types[current].extend(line[7:60].split())
        xyz = None
        if "APPROX POSITION XYZ" in g:
            vals = g["APPROX POSITION XYZ"][0][:42].split()
            if len(vals) == 3:
                xyz = (float(vals[0]), float(vals[1]), float(vals[2]))
        tsys = "GPS"
        if "TIME OF FIRST OBS" in g:
            tsys = g["TIME OF FIRST OBS"][0][48:51].strip() or "GPS"
        interval = None
        if "INTERVAL" in g:
            interval = _float(g["INTERVAL"][0][:10])
        bds = types.get("C", [])
        code = next((c for c in _B1I_CODES if f"C{c}" in bds), None)
        if code is None and bds:
            log.warning("%s: no B1I code (C2I/C1I) among BDS types %s", self.path, bds)
        return ObsHeader(
            version=version,
            marker_name=g.get("MARKER NAME", [""])[0][:60].strip(),
            receiver_type=g.get("REC # / TYPE / VERS", [" " * 40])[0][20:40].strip(),
            approx_xyz_m=xyz,
            time_system=tsys,
            obs_types={k: tuple(v) for k, v in types.items()},
            bds_code=code,
            interval_s=interval,
        )

    def __iter__(self) -> Iterator[MeasurementEpoch]:
        h = self.header
        types = h.obs_types.get("C", ())
        code = h.bds_code
        idx = {t: i for i, t in enumerate(types)}
        i_pr = idx.get(f"C{code}") if code else None
        i_cn0 = idx.get(f"S{code}") if code else None
        i_dop = idx.get(f"D{code}") if code else None
        shift_s = BDT_GPST_OFFSET_S if h.time_system == "BDT" else 0.0
        if h.time_system not in ("GPS", "BDT", "MIXED", ""):
            log.warning("%s: time system %s read as GPST", self.path, h.time_system)
        with self.path.open("r", encoding="ascii", errors="replace") as fh:
            lineno = 0
            for _ in range(self._header_lines):
                next(fh)
                lineno += 1
            for line in fh:
                lineno += 1
                if not line.strip():
                    continue
                if line[0] != ">":
                    raise FramingError(
                        f"{self.path}:{lineno}: expected an epoch line ('>'), "
                        f"got {line.rstrip()[:40]!r}"
                    )
                try:
                    parts = line[1:].split()
                    t = _epoch_datetime(parts[:6])
                    flag = int(line[31:32])
                    nsat = int(line[32:35])
                except (ValueError, IndexError) as exc:
                    raise FramingError(
                        f"{self.path}:{lineno}: bad epoch line {line.rstrip()!r}: {exc}"
                    ) from exc
                body: list[str] = []
                for _ in range(nsat):
                    nxt = fh.readline()
                    lineno += 1
                    if not nxt:
                        raise FramingError(f"{self.path}:{lineno}: file ends inside an epoch")
                    body.append(nxt)
                if flag > 1:
                    continue  # 2-5: header/event lines; 6: cycle-slip records
                week, tow = gpst_from_datetime(t)
                week, tow = normalize(week, tow + shift_s)
                yield self._epoch(week, tow, body, i_pr, i_cn0, i_dop, lineno - nsat)

    def _epoch(
        self,
        week: int,
        tow: float,
        body: list[str],
        i_pr: int | None,
        i_cn0: int | None,
        i_dop: int | None,
        first_line: int,
    ) -> MeasurementEpoch:
        prn: list[str] = []
        pr: list[float] = []
        cn0: list[float] = []
        dop: list[float] = []

        def obs(rec: str, i: int | None) -> float:
            if i is None:
                return math.nan
            return _float(rec[3 + 16 * i : 3 + 16 * i + 14])

        for k, rec in enumerate(body):
            if rec[0] != "C" or i_pr is None:
                continue
            try:
                value = obs(rec, i_pr)
                if not value > 0:
                    continue
                prn.append(_sat_id(rec[:3]))
                pr.append(value)
                cn0.append(obs(rec, i_cn0))
                dop.append(obs(rec, i_dop))
            except ValueError as exc:
                raise FramingError(f"{self.path}:{first_line + k}: bad observation: {exc}") from exc
        code = self.header.bds_code or "2I"
        return MeasurementEpoch.from_columns(
            week,
            tow,
            prn,
            [code] * len(prn),
            np.array(pr),
            cn0_dbhz=cn0,
            doppler_hz=dop,
            source="rinex",
        )


def iter_obs(path: str | Path) -> Iterator[MeasurementEpoch]:
    """BDS B1I epochs of a RINEX 3 observation file."""
    return iter(RinexObsReader(path))


@dataclass(frozen=True, slots=True)
class NavData:
    """BDS content of one or more RINEX 3 navigation files."""

    version: float
    ephemerides: dict[str, tuple[Ephemeris, ...]]
    iono_bds: KlobucharParams | None = None
    iono_gps: KlobucharParams | None = None
    leap_seconds: int | None = None


def _iono(
    lines: list[str], a: str, b: str, system: Literal["BDS", "GPS"]
) -> KlobucharParams | None:
    vals: dict[str, tuple[float, ...]] = {}
    for line in lines:
        key = line[:4].strip()
        if key in (a, b):
            vals[key] = tuple(_float(line[5 + 12 * i : 17 + 12 * i]) for i in range(4))
    if a in vals and b in vals:
        al, be = vals[a], vals[b]
        return KlobucharParams(
            alpha=(al[0], al[1], al[2], al[3]), beta=(be[0], be[1], be[2], be[3]), system=system
        )
    return None


def _bds_ephemeris(prn: str, rec: list[str], path: Path, lineno: int) -> tuple[Ephemeris, float]:
    """The record's ephemeris and its transmission time (BDT seconds of week)."""
    """The record's ephemeris and its transmission time (BDT seconds of week)."""
    first = rec[0]
    try:
        toc_t = _epoch_datetime(first[4:23].split())
        vals = [_float(first[23 + 19 * i : 42 + 19 * i]) for i in range(3)]
        for line in rec[1:]:
            vals.extend(_float(line[4 + 19 * i : 23 + 19 * i]) for i in range(4))
    except (ValueError, IndexError) as exc:
        raise FramingError(f"{path}:{lineno}: bad BDS navigation record: {exc}") from exc
    v = vals + [math.nan] * (31 - len(vals))
    (
        af0,
        af1,
        af2,
        aode,
        crs,
        dn,
        m0,
        cuc,
        e,
        cus,
        sqrt_a,
        toe,
        cic,
        om0,
        cis,
        i0,
        crc,
        om,
        omdot,
        idot,
        _s1,
        week,
        _s2,
        ura,
        sath1,
        tgd1,
        tgd2,
        tot,
        aodc,
    ) = v[:29]
    if any(math.isnan(x) for x in (sqrt_a, e, toe, m0, week)):
        raise FramingError(f"{path}:{lineno}: incomplete BDS navigation record for {prn}")
    _, toc_sow = gpst_from_datetime(toc_t)  # BDT calendar -> BDT seconds of week
    eph = Ephemeris(
        prn=prn,
        week=int(week),
        toe_sow_s=toe,
        toc_sow_s=toc_sow,
        af0_s=af0,
        af1_s_s=af1,
        af2_s_s2=af2,
        sqrt_a_sqrt_m=sqrt_a,
        e=e,
        i0_rad=i0,
        omega0_rad=om0,
        omega_rad=om,
        m0_rad=m0,
        delta_n_rad_s=dn,
        omega_dot_rad_s=omdot,
        idot_rad_s=idot,
        cuc_rad=cuc,
        cus_rad=cus,
        crc_m=crc,
        crs_m=crs,
        cic_rad=cic,
        cis_rad=cis,
        tgd1_s=0.0 if math.isnan(tgd1) else tgd1,
        tgd2_s=0.0 if math.isnan(tgd2) else tgd2,
        health=0 if math.isnan(sath1) else int(sath1),
        aode=0 if math.isnan(aode) else int(aode),
        aodc=0 if math.isnan(aodc) else int(aodc),
        ura_m=0.0 if math.isnan(ura) else ura,
        source="rinex",
    )
    return eph, (-math.inf if math.isnan(tot) else tot)


def read_nav(path: str | Path) -> NavData:
    """BDS ephemerides and ionosphere coefficients of a RINEX 3 nav file (mixed or BDS-only)."""
    path = Path(path)
    try:
        fh = path.open("r", encoding="ascii", errors="replace")
    except OSError as exc:
        raise FramingError(f"{path}: cannot read: {exc.strerror}") from exc
    with fh:
        groups, lineno = _read_header(fh, path, "N")
        version = float(groups["RINEX VERSION / TYPE"][0][:9])
        iono_lines = groups.get("IONOSPHERIC CORR", [])
        leap = None
        if "LEAP SECONDS" in groups:
            try:
                leap = int(groups["LEAP SECONDS"][0][:6])
            except ValueError:
                leap = None
        ephs: dict[str, dict[tuple[int, float], Ephemeris]] = {}
        tot_of: dict[tuple[str, tuple[int, float]], float] = {}
        for line in fh:
            lineno += 1
            if not line.strip():
                continue
            sys_char = line[0]
            if sys_char not in _NAV_LINES:
                raise FramingError(
                    f"{path}:{lineno}: expected a navigation record, got {line.rstrip()[:40]!r}"
                )
            start = lineno
            rec = [line]
            for _ in range(_NAV_LINES[sys_char] - 1):
                nxt = fh.readline()
                lineno += 1
                if not nxt:
                    raise FramingError(f"{path}:{lineno}: file ends inside a navigation record")
                rec.append(nxt)
            if sys_char != "C":
                continue
            prn = _sat_id(line[:3])
            eph, tot = _bds_ephemeris(prn, rec, path, start)
            key = (eph.week, eph.toe_sow_s)
            held = ephs.setdefault(prn, {})
            # The same set may be repeated; the latest transmission (e.g. a health change) wins.
            if key not in held or tot >= tot_of[(prn, key)]:
                held[key] = eph
                tot_of[(prn, key)] = tot
    return NavData(
        version=version,
        ephemerides={p: tuple(d.values()) for p, d in sorted(ephs.items())},
        iono_bds=_iono(iono_lines, "BDSA", "BDSB", "BDS"),
        iono_gps=_iono(iono_lines, "GPSA", "GPSB", "GPS"),
        leap_seconds=leap,
    )


def merge_nav(*navs: NavData) -> NavData:
    """Union of several nav files; the first file's ionosphere coefficients win."""
    ephs: dict[str, dict[tuple[int, float], Ephemeris]] = {}
    for nav in navs:
        for prn, items in nav.ephemerides.items():
            for e in items:
                ephs.setdefault(prn, {}).setdefault((e.week, e.toe_sow_s), e)
    return NavData(
        version=max(n.version for n in navs),
        ephemerides={p: tuple(d.values()) for p, d in sorted(ephs.items())},
        iono_bds=next((n.iono_bds for n in navs if n.iono_bds), None),
        iono_gps=next((n.iono_gps for n in navs if n.iono_gps), None),
        leap_seconds=next((n.leap_seconds for n in navs if n.leap_seconds is not None), None),
    )
