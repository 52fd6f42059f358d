"""Streaming RINEX 3 and 4 readers (observation and navigation), versions 3.02-3.05 and
4.00-4.02.

Format: "RINEX, The Receiver Independent Exchange Format", versions 3.04 (IGS/RTCM-SC104,
2018), 3.05 (2020) and 4.00 (2021). What this module relies on, by section:

- Header records (Appendix, "GNSS observation data file - header section description" and
  "GNSS navigation message file - header section description"): labels in columns 61-80,
  the first record is ``RINEX VERSION / TYPE`` (F9.2 version, file type in column 21,
  satellite system in column 41), the last ``END OF HEADER``.
- ``SYS / # / OBS TYPES`` (section 5.2, "Satellite system-dependent list of observables"):
  A1,2X,I3 then 13 types of 1X,A3 per line, continued on lines that start blank. Each
  observation field is indexed by its position in this list, so a receiver-specific leading
  type (e.g. Septentrio's ``X1`` channel) is simply one more column.
- BDS observation codes (section 5.1, Table 9 in 3.04): B1I is band 2 (``C2I``) from 3.03
  on; RINEX 3.02 called it band 1 (``C1I``). The reader takes whatever the header lists for
  system C, preferring ``C2I`` then ``C1I``.
- Satellite numbers (section 3.5): ``snn``; writers that print ``C 1`` are read as ``C01``.
- ``TIME OF FIRST OBS`` time system (section 3.1): GPS, GLO, GAL, QZS, BDT or IRN; the
  default follows the file's satellite system. BDT epochs become GPST by +14 s
  (BDS-SIS-ICD-B1I-3.0 section 4.2 via :mod:`service.core.timebase`); GLO (UTC(SU) + 3 h)
  via the leap-second table.
- Observation data records (Appendix, "GNSS observation data file - data record
  description"; event flags, section 5.3.x of 3.05 / "Event flag records"): an epoch line
  ``> yyyy mm dd hh mm ss.sssssss  f nnn``. Flags 0 and 1 are followed by ``nnn``
  observation records, one line per satellite, 16 characters per observation (F14.3 value,
  LLI, signal strength). Flags 2-5 are followed by ``nnn`` special records (header lines,
  new site occupation, external event; the epoch time may be blank for 2-4); flag 6 by
  ``nnn`` cycle-slip records. Header records after flag 4 may redefine the type lists.
- Navigation data records (Appendix, one table per system; BDS is Table A14 in 3.04):
  ``A1,I2.2,1X,I4,5(1X,I2.2),3D19.12`` then lines of ``4X,4D19.12``. GPS, Galileo, QZSS,
  BDS and IRNSS records have 8 lines; SBAS 4; GLONASS 4, and 5 from 3.05 on (the 3.05
  status/health line). Fields are cut at fixed columns, so numbers that run together and
  Fortran ``D`` exponents are read correctly. The toc of a BDS record is BDT.
- ``IONOSPHERIC CORR`` (A4,1X,4D12.4): ``BDSA``/``BDSB`` and ``GPSA``/``GPSB``;
  ``LEAP SECONDS`` (4I6,A3; identifier ``BDS`` or blank).
- RINEX 4 (4.00, section 5.4 and the navigation appendix): an observation file is read as
  a 3.05 one; a navigation file's records each open with a line ``> TYPE SV MSG`` (``EPH``,
  ``STO``, ``EOP``, ``ION``) and run to the next. The ``EPH`` records of GPS/QZSS/NavIC LNAV,
  Galileo I/NAV and F/NAV, BeiDou D1 and D2, SBAS and GLONASS FDMA hold the RINEX 3 record
  of their system; the Klobuchar coefficients come in ``ION`` records (BeiDou ``D1D2``,
  GPS ``LNAV``: the transmission epoch and three D19.12 fields, then lines of 4X,4D19.12),
  the header's ``IONOSPHERIC CORR`` being gone. Other records (CNAV, CNV1-3, ``STO``,
  ``EOP`` ...) are skipped, counted ``records4_<TYPE>_<system>_<MSG>``. The GST - GPST
  offset, a ``TIME SYSTEM CORR`` header record in RINEX 3, is an ``STO`` record in RINEX 4:
  not read (it is only ever recorded, :class:`~service.core.types.TimeOffset`).

A malformed file raises :class:`~service.core.errors.FramingError` whose message starts with
``<file>:<1-based line>:``. A *lenient* observation reader (``RinexObsReader(path,
lenient=True)``, used by stream replay) raises only for a malformed header; in the data
section it logs the same message, counts what it drops and resynchronises at the next epoch
line (the ``>`` record identifier of the RINEX 3 data record description):

- a broken epoch line, an epoch whose records run into the next ``>`` line or past the end
  of the file, or a flag 4 header record that does not parse: the epoch is skipped
  (``epochs_skipped``);
- an unreadable observation record: that record is skipped, the rest of the epoch is kept
  (``records_skipped``);
- lines that belong to no epoch (before the next ``>``): ``lines_skipped``.

An epoch flag above 6 (RINEX 3 defines 0-6) is not damage to the framing: the epoch and its
announced records are skipped with a warning and counted (``epochs_skipped``) by both
readers, so ``bdsfix solve`` and ``bdsfix replay`` read such a file alike. So is a
satellite's record repeated in an epoch (RINEX 3 has one record per satellite in an epoch):
the first is kept, the later ones are the same measurement again and are dropped by both
readers, counted (``duplicate_records``) with a warning at the first
(:meth:`service.core.types.MeasurementEpoch.from_columns` drops them); solved twice they
would double the satellite's weight and shrink the protection levels.
"""

from __future__ import annotations

import datetime as dt
import gzip
import io
import logging
import math
import weakref
import zlib
from collections import Counter
from collections.abc import Callable, Generator, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

import numpy as np

from service.core.bds_nav import klobuchar_on_grid
from service.core.errors import ConfigError, FramingError
from service.core.ntripurl import looks_like_url
from service.core.systems import GnssSystem
from service.core.timebase import (
    BDT_GPS_WEEK_OFFSET,
    BDT_GPST_OFFSET_S,
    bdt_to_gpst,
    gpst_from_utc,
    gpst_to_bdt,
    toe_gpst_to_bdt,
)
from service.core.types import Ephemeris, KlobucharParams, MeasurementEpoch, TimeOffset

log = logging.getLogger(__name__)

_GPS_EPOCH_ORDINAL = dt.date(1980, 1, 6).toordinal()
_BDT_EPOCH_ORDINAL = dt.date(2006, 1, 1).toordinal()

_READ = GnssSystem.BDS.value
"""The system letter whose observations are read (BeiDou); the records of the others are
counted and skipped."""

_B1I_CODES = ("2I", "1I")
"""B1I code suffixes in order of preference: the 3.03+ name, then the 3.02 one."""

_DEFAULT_TIME_SYSTEM: dict[str, str] = {
    GnssSystem.GPS: "GPS",
    GnssSystem.GLO: "GLO",
    GnssSystem.GAL: "GAL",
    GnssSystem.QZS: "QZS",
    GnssSystem.BDS: "BDT",
    GnssSystem.IRN: "IRN",
}
_GPS_ALIGNED = frozenset({"GPS", "GAL", "QZS", "IRN"})
"""Time systems whose RINEX calendar epochs read directly as GPST (section 3.1)."""

_NAV_RECORD_LINES: dict[str, int] = {
    GnssSystem.GPS: 8,
    GnssSystem.GAL: 8,
    GnssSystem.QZS: 8,
    GnssSystem.BDS: 8,
    GnssSystem.IRN: 8,
    GnssSystem.SBAS: 4,
    GnssSystem.GLO: 4,
}
"""Lines per navigation record by system (GLONASS: 5 from RINEX 3.05 on)."""

_BDS_RECORD: tuple[tuple[str | None, ...], ...] = (
    ("af0_s", "af1_s_s", "af2_s_s2"),  # SV / EPOCH / SV CLK (after the BDT toc epoch)
    ("aode", "crs_m", "delta_n_rad_s", "m0_rad"),  # BROADCAST ORBIT - 1
    ("cuc_rad", "e", "cus_rad", "sqrt_a_sqrt_m"),  # BROADCAST ORBIT - 2
    ("toe_sow_s", "cic_rad", "omega0_rad", "cis_rad"),  # BROADCAST ORBIT - 3 (toe: BDT sow)
    ("i0_rad", "crc_m", "omega_rad", "omega_dot_rad_s"),  # BROADCAST ORBIT - 4
    ("idot_rad_s", None, "week", None),  # BROADCAST ORBIT - 5 (spare, BDT week, spare)
    ("ura_m", "health", "tgd1_s", "tgd2_s"),  # BROADCAST ORBIT - 6 (SatH1, TGD1 B1/B3, TGD2)
    ("tot_sow_s", "aodc", None, None),  # BROADCAST ORBIT - 7 (transmission time, AODC)
)
"""BDS navigation data record (RINEX 3.04 Table A14), one tuple per line; None = spare."""

_GPS_RECORD: tuple[tuple[str | None, ...], ...] = (
    ("af0_s", "af1_s_s", "af2_s_s2"),  # SV / EPOCH / SV CLK (after the GPST toc epoch)
    ("aode", "crs_m", "delta_n_rad_s", "m0_rad"),  # BROADCAST ORBIT - 1 (IODE)
    ("cuc_rad", "e", "cus_rad", "sqrt_a_sqrt_m"),  # BROADCAST ORBIT - 2
    ("toe_sow_s", "cic_rad", "omega0_rad", "cis_rad"),  # BROADCAST ORBIT - 3 (toe: GPST sow)
    ("i0_rad", "crc_m", "omega_rad", "omega_dot_rad_s"),  # BROADCAST ORBIT - 4
    ("idot_rad_s", None, "week", None),  # BROADCAST ORBIT - 5 (L2 codes, GPS week, L2 P flag)
    ("ura_m", "health", "tgd1_s", "aodc"),  # BROADCAST ORBIT - 6 (URA m, SV health, TGD, IODC)
    ("tot_sow_s", None, None, None),  # BROADCAST ORBIT - 7 (transmission time, fit interval)
)
"""GPS navigation data record (RINEX 3.04 Table A6; QZSS Table A10 is the same)."""

_GAL_RECORD: tuple[tuple[str | None, ...], ...] = (
    ("af0_s", "af1_s_s", "af2_s_s2"),  # SV / EPOCH / SV CLK (after the GST toc epoch)
    ("aode", "crs_m", "delta_n_rad_s", "m0_rad"),  # BROADCAST ORBIT - 1 (IODnav)
    ("cuc_rad", "e", "cus_rad", "sqrt_a_sqrt_m"),  # BROADCAST ORBIT - 2
    ("toe_sow_s", "cic_rad", "omega0_rad", "cis_rad"),  # BROADCAST ORBIT - 3 (toe: GST sow)
    ("i0_rad", "crc_m", "omega_rad", "omega_dot_rad_s"),  # BROADCAST ORBIT - 4
    ("idot_rad_s", "data_sources", "week", None),  # BROADCAST ORBIT - 5 (GAL week = GPS week)
    ("ura_m", "health", "bgd_e5a_s", "bgd_e5b_s"),  # BROADCAST ORBIT - 6 (SISA m, SV health)
    ("tot_sow_s", None, None, None),  # BROADCAST ORBIT - 7 (transmission time)
)
"""Galileo navigation data record (RINEX 3.04 Table A8): I/NAV or F/NAV by its data
sources (bit 0 I/NAV E1-B, bit 1 F/NAV E5a-I, bit 2 I/NAV E5b-I; bit 8 clock for E5a,E1,
bit 9 for E5b,E1)."""

_RECORDS: dict[str, tuple[tuple[str | None, ...], ...]] = {
    GnssSystem.BDS: _BDS_RECORD,
    GnssSystem.GPS: _GPS_RECORD,
    GnssSystem.GAL: _GAL_RECORD,
}
"""The systems whose navigation records are read, with their layouts; the others' records are
counted and skipped."""
_SYSTEM_NAMES = {GnssSystem.BDS: "BDS", GnssSystem.GPS: "GPS", GnssSystem.GAL: "Galileo"}

_INT_FIELDS = frozenset({"aode", "aodc", "health", "week", "data_sources"})
_FIELD_COLUMNS: dict[str, tuple[tuple[int, tuple[tuple[str, int, int], ...]], ...]] = {
    system: tuple(
        (
            k,
            tuple(
                (name, start + 19 * j, start + 19 * (j + 1))
                for j, name in enumerate(names)
                if name is not None
            ),
        )
        for k, names in enumerate(layout)
        for start in (23 if k == 0 else 4,)
    )
    for system, layout in _RECORDS.items()
}
"""Per system, each record line's index and its fields' (name, first column, end column):
4X,4D19.12 (the first line after its 23 columns of ID and epoch), one per :data:`_RECORDS`
name."""
_INT_FIELDS_OF: dict[str, tuple[str, ...]] = {
    system: tuple(name for names in layout for name in names if name in _INT_FIELDS)
    for system, layout in _RECORDS.items()
}
"""Per system, the integer fields of its record, in record order."""
_OPTIONAL = {
    "tgd1_s": 0.0,
    "tgd2_s": 0.0,
    "ura_m": 0.0,
    "aode": 0,
    "aodc": 0,
    "health": 0,
    "data_sources": 0,
    "bgd_e5a_s": 0.0,
    "bgd_e5b_s": 0.0,
}
"""Fields a writer may leave blank, with the value used then; every other one is required."""
_GAL_INAV = 0b101
"""Data-source bits of an I/NAV set (E1-B, E5b-I): its clock is for E1,E5b, and a
single-frequency E1 user takes BGD(E1,E5b) (OS SIS ICD 5.1.5)."""


def _sat_id(text: str) -> str:
    """``C 1``/``C01``/``C1`` -> ``C01`` (section 3.5)."""
    num = text[1:].strip()
    return f"{text[0]}{int(num):02d}" if num.isdigit() else text.strip()


def _float(text: str) -> float:
    """A Fortran F/E/D field; blank is NaN. ``float`` first (it skips the blanks around a
    number itself): only a blank or a D exponent takes the second look."""
    try:
        return float(text)
    except ValueError:
        pass
    t = text.strip()
    if not t:
        return math.nan
    return float(t.replace("D", "E").replace("d", "e"))


class _Lines:
    """A text file read line by line with a 1-based line counter and one line of push-back."""

    def __init__(self, fh: IO[str], path: Path) -> None:
        self._fh = fh
        self.path = path
        self.n = 0
        self._back: str | None = None

    def next(self) -> str | None:
        if self._back is not None:
            line, self._back = self._back, None
        else:
            line = self._fh.readline()
            if not line:
                return None
        self.n += 1
        return line

    def push_back(self, line: str) -> None:
        self._back = line
        self.n -= 1

    def rest(self) -> list[str]:
        """Every line not read yet, at once (a pushed-back line first); :attr:`n` stays the
        number of the last line read before."""
        back, self._back = self._back, None
        return ([back] if back is not None else []) + list(self._fh)

    def error(self, message: str, lineno: int | None = None) -> FramingError:
        return FramingError(f"{self.path}:{self.n if lineno is None else lineno}: {message}")


_GZIP_MAGIC = b"\x1f\x8b"
_COMPRESS_MAGIC = b"\x1f\x9d"  # Unix compress (.Z), as older IGS archives have it
COMPRESSED_MAGICS = (_GZIP_MAGIC, _COMPRESS_MAGIC)
"""First bytes of the compressed forms :func:`open_text` reads (gzip, Unix compress)."""
_CRINEX_LABEL = b"CRINEX VERS   / TYPE"


class _GzipText(io.TextIOWrapper):
    """gzip text whose damage (truncation, bad CRC) is a FramingError naming the file."""

    def __init__(self, path: Path) -> None:
        self._path = path
        super().__init__(gzip.open(path, "rb"), encoding="ascii", errors="replace")  # noqa: SIM115

    def _damaged(self, exc: Exception) -> FramingError:
        return FramingError(f"{self._path}: damaged gzip file: {exc}")

    def readline(self, size: int = -1, /) -> str:  # type: ignore[override]
        try:
            return super().readline(size)
        except (EOFError, OSError, zlib.error) as exc:
            raise self._damaged(exc) from exc

    def __next__(self) -> str:  # type: ignore[override]
        try:
            return super().__next__()
        except (EOFError, OSError, zlib.error) as exc:
            raise self._damaged(exc) from exc


def open_text(path: str | Path) -> IO[str]:
    """A RINEX file as text, whatever the form IGS publishes it in: plain, gzip (``.gz``),
    Unix compress (``.Z``) or Hatanaka compact RINEX (``.crx``/``.??d``, plain or
    compressed; decompressed with the ``hatanaka`` package). The form is read from the
    file's first bytes, not its name. Plain and gzip files stream; the others are expanded
    in memory."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(2)
        if head == _GZIP_MAGIC:
            with gzip.open(path, "rb") as gz:
                first = gz.readline(200)
            if _CRINEX_LABEL not in first:
                return _GzipText(path)
        elif head != _COMPRESS_MAGIC:
            with path.open("rb") as fh:
                first = fh.readline(200)
            if _CRINEX_LABEL not in first:
                return path.open("r", encoding="ascii", errors="replace")
    except OSError as exc:  # includes gzip.BadGzipFile
        raise FramingError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    import hatanaka

    try:
        text = hatanaka.decompress(path).decode("ascii", errors="replace")
    except (OSError, ValueError, RuntimeError) as exc:
        raise FramingError(f"{path}: cannot decompress (gzip/.Z/Hatanaka): {exc}") from exc
    return io.StringIO(text)


def _open(path: Path) -> IO[str]:
    return open_text(path)


@dataclass(frozen=True, slots=True)
class _Header:
    version: float
    file_type: str
    system: str
    records: dict[str, list[tuple[int, str]]]  # label -> [(line number, text)]

    def first(self, label: str) -> str | None:
        got = self.records.get(label)
        return got[0][1] if got else None


def _read_header(lines: _Lines, kind: str) -> _Header:
    """Header records grouped by label (columns 61-80), up to ``END OF HEADER``."""
    records: dict[str, list[tuple[int, str]]] = {}
    first = lines.next()
    if first is None:
        raise lines.error("empty file, not RINEX", 1)
    if first[60:80].strip() != "RINEX VERSION / TYPE":
        raise lines.error("not a RINEX file (first record is not RINEX VERSION / TYPE)")
    try:
        version = float(first[:9])
    except ValueError as exc:
        raise lines.error(f"bad RINEX version {first[:9].strip()!r}") from exc
    if not 3.0 <= version < 5.0:
        raise lines.error(
            f"RINEX version {version:.2f} is not 3.xx or 4.xx (this reader reads RINEX "
            "3.02-3.05 and 4.00-4.02)"
        )
    file_type = first[20:21]
    if file_type != kind:
        raise lines.error(f"file type {file_type!r}, expected {kind!r}")
    records["RINEX VERSION / TYPE"] = [(1, first)]
    while (line := lines.next()) is not None:
        label = line[60:80].strip()
        records.setdefault(label, []).append((lines.n, line.rstrip("\r\n")))
        if label == "END OF HEADER":
            return _Header(version, file_type, first[40:41].strip() or "G", records)
    raise lines.error("no END OF HEADER")


def _obs_types(
    lines: list[tuple[int, str]], path: Path, into: dict[str, tuple[str, ...]] | None = None
) -> dict[str, tuple[str, ...]]:
    """Parse ``SYS / # / OBS TYPES`` records (with continuation lines) per system."""
    out: dict[str, tuple[str, ...]] = dict(into or {})
    current = ""
    count = 0
    got: list[str] = []
    start = 0

    def close() -> None:
        if current:
            if len(got) != count:
                raise FramingError(
                    f"{path}:{start}: SYS / # / OBS TYPES for {current} announces {count} "
                    f"types, lists {len(got)}"
                )
            out[current] = tuple(got)

    for lineno, text in lines:
        if text[:1].strip():
            close()
            current, start, got = text[0], lineno, []
            try:
                count = int(text[3:6])
            except ValueError as exc:
                raise FramingError(f"{path}:{lineno}: bad SYS / # / OBS TYPES count") from exc
        elif not current:
            raise FramingError(f"{path}:{lineno}: SYS / # / OBS TYPES continuation first")
        got.extend(text[7:60].split())
    close()
    return out


@dataclass(frozen=True, slots=True)
class ObsHeader:
    """What a RINEX 3 observation header says.

    ``approx_xyz_m`` is None when absent or written as zeros (an unknown position);
    ``time_system`` is the epochs' time scale; ``bds_code`` the B1I code suffix (``"2I"`` or
    ``"1I"``) chosen from ``obs_types["C"]``, None when the file has no B1I pseudorange.
    """

    version: float
    marker_name: str = ""
    receiver_type: str = ""
    approx_xyz_m: tuple[float, float, float] | None = None
    time_system: str = "GPS"
    obs_types: dict[str, tuple[str, ...]] = field(default_factory=dict)
    bds_code: str | None = None
    interval_s: float | None = None
    satellite_system: str = "M"


def _choose_bds_code(types: tuple[str, ...]) -> str | None:
    return next((c for c in _B1I_CODES if f"C{c}" in types), None)


def _parse_obs_header(h: _Header, path: Path) -> ObsHeader:
    types = _obs_types(h.records.get("SYS / # / OBS TYPES", []), path)
    xyz = None
    if (line := h.first("APPROX POSITION XYZ")) is not None:
        try:
            x, y, z = (float(line[14 * i : 14 * i + 14]) for i in range(3))
        except ValueError:
            log.warning("%s: unreadable APPROX POSITION XYZ %r", path, line[:42])
        else:
            xyz = None if x == y == z == 0.0 else (x, y, z)
    tsys = _DEFAULT_TIME_SYSTEM.get(h.system, "GPS")
    if (line := h.first("TIME OF FIRST OBS")) is not None:
        tsys = line[48:51].strip() or tsys
    else:
        log.warning("%s: no TIME OF FIRST OBS; epochs read as %s", path, tsys)
    if tsys not in _GPS_ALIGNED | {"BDT", "GLO"}:
        lineno = h.records["TIME OF FIRST OBS"][0][0]
        raise FramingError(f"{path}:{lineno}: unknown time system {tsys!r}")
    interval = None
    if (line := h.first("INTERVAL")) is not None:
        interval = _float(line[:10])
        interval = None if math.isnan(interval) else interval
    bds = types.get(_READ, ())
    code = _choose_bds_code(bds)
    if code is None and bds:
        log.warning("%s: no B1I code (C2I/C1I) among the BDS types %s", path, " ".join(bds))
    rec = h.first("REC # / TYPE / VERS") or ""
    return ObsHeader(
        version=h.version,
        marker_name=(h.first("MARKER NAME") or "")[:60].strip(),
        receiver_type=rec[20:40].strip(),
        approx_xyz_m=xyz,
        time_system=tsys,
        obs_types=types,
        bds_code=code,
        interval_s=interval,
        satellite_system=h.system,
    )


_CODES: dict[str, tuple[str, ...]] = {
    GnssSystem.BDS: _B1I_CODES,
    GnssSystem.GPS: ("1C",),
    GnssSystem.GAL: ("1C", "1X", "1B"),
}
"""Per system read, the code suffixes of the one signal bdsfix ranges on, by preference:
BDS B1I (``2I``, 3.02's ``1I``), GPS L1 C/A (``1C``), Galileo E1 (``1C`` pilot, ``1X``
data+pilot, ``1B`` data; RINEX 3.04 Table 6), as the header declares them."""


@dataclass(frozen=True, slots=True)
class _Columns:
    """Character offsets of one system's signal fields in its observation records."""

    code: str | None
    pr: int | None
    cn0: int | None
    doppler: int | None

    @classmethod
    def from_types(cls, system: str, types: tuple[str, ...]) -> _Columns:
        code = next((c for c in _CODES[system] if f"C{c}" in types), None)
        if code is None:
            return cls(None, None, None, None)
        idx = {t: 3 + 16 * i for i, t in enumerate(types)}
        return cls(code, idx[f"C{code}"], idx.get(f"S{code}"), idx.get(f"D{code}"))


def _columns(systems: frozenset[str], types: dict[str, tuple[str, ...]]) -> dict[str, _Columns]:
    return {k: _Columns.from_types(k, types.get(k, ())) for k in systems}


class RinexObsReader:
    """The BDS B1I (and, among ``systems``, GPS L1 C/A and Galileo E1: :data:`_CODES`)
    measurements of a RINEX 3 observation file, epoch by epoch.

    The header is read on construction (:attr:`header`); iterating streams the data
    section, one :class:`~service.core.types.MeasurementEpoch` per observation epoch (flags 0
    and 1), with the satellites of ``systems`` (RINEX letters; BeiDou alone by default) that
    carry a non-zero pseudorange of their signal. Epochs without any are yielded empty.
    Times are GPST. :attr:`counters` counts what was read and skipped; a malformed record
    raises :class:`~service.core.errors.FramingError`, or with ``lenient`` is logged
    (``file:line``), counted and skipped (see the module docstring). A malformed header
    raises in both modes.
    """

    def __init__(
        self, path: str | Path, *, lenient: bool = False, systems: Iterable[str] = (_READ,)
    ) -> None:
        self.path = Path(path)
        self.lenient = lenient
        self.systems = frozenset(systems) & frozenset(_CODES)
        with _open(self.path) as fh:
            lines = _Lines(fh, self.path)
            raw = _read_header(lines, "O")
            self._data_offset = fh.tell()
        self._header_lines = lines.n
        self.header = _parse_obs_header(raw, self.path)
        self.counters: Counter[str] = Counter()
        self._live: weakref.WeakSet[Generator[MeasurementEpoch, None, None]] = weakref.WeakSet()

    def __iter__(self) -> Iterator[MeasurementEpoch]:
        gen = self._epochs()
        self._live.add(gen)
        return gen

    def close(self) -> None:
        """Close the file of any iteration still open."""
        for gen in list(self._live):
            gen.close()

    def __enter__(self) -> RinexObsReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _to_gpst(self, days: int, sod_s: float) -> tuple[int, float]:
        """Calendar (days since 1980-01-06, seconds of day) on the file's scale -> GPST."""
        tsys = self.header.time_system
        week, dow = divmod(days, 7)
        sow = dow * 86400 + sod_s
        if tsys in _GPS_ALIGNED:
            return week, sow
        if tsys == "BDT":
            return bdt_to_gpst(week - BDT_GPS_WEEK_OFFSET, sow)
        # GLO: UTC(SU) + 3 h
        whole = math.floor(sod_s)
        utc = dt.datetime.fromordinal(_GPS_EPOCH_ORDINAL + days) + dt.timedelta(
            seconds=whole - 3 * 3600
        )
        week, tow = gpst_from_utc(utc)
        return week, tow + (sod_s - whole)

    def _epochs(self) -> Generator[MeasurementEpoch, None, None]:
        types = dict(self.header.obs_types)
        cols = _columns(self.systems, types)
        counters = self.counters
        with _open(self.path) as fh:
            fh.seek(self._data_offset)
            lines = _Lines(fh, self.path)
            lines.n = self._header_lines
            stray = 0  # lines outside any epoch since the last one (lenient mode)
            while (line := lines.next()) is not None:
                if not line.strip():
                    counters["blank_lines"] += 1
                    continue
                if line[0] != ">":
                    err = lines.error(
                        f"expected an epoch line ('>'), got {line.rstrip()[:40]!r} "
                        "(more records than the previous epoch line announced?)"
                    )
                    if not self.lenient:
                        raise err
                    if not stray:
                        log.warning("%s; skipping to the next epoch line", err)
                    stray += 1
                    counters["lines_skipped"] += 1
                    continue
                stray = 0
                try:
                    flag, count, when = self._epoch_line(line, lines)
                    body_start = lines.n + 1
                    body = self._body(count, body_start, lines)
                    if flag > 6:
                        self._unknown_flag(flag, body, body_start - 1, counters)
                        continue
                    if flag >= 2:
                        self._special(flag, body, body_start, types, counters)
                        if flag == 4:
                            cols = _columns(self.systems, types)
                        continue
                    if when is None:  # only flags 2-4 may leave the time blank
                        raise lines.error("observation epoch without a time", body_start - 1)
                    epoch = self._epoch(when, body, body_start, cols, lines)
                except FramingError as exc:
                    if not self.lenient:
                        raise
                    counters["epochs_skipped"] += 1
                    log.warning("%s; epoch skipped", exc)
                    stray = 1  # its records follow: skipped without another warning
                    continue
                counters["epochs"] += 1
                counters["epochs_power_failure"] += flag == 1
                yield epoch

    def _body(self, count: int, first: int, lines: _Lines) -> list[str]:
        """The ``count`` records after an epoch line (first at line ``first``).

        A lenient reader stops at a ``>`` line, which no record starts with, and hands it
        back to the epoch loop, so a wrong count costs one epoch, not the ones after it.
        """
        body: list[str] = []
        for _ in range(count):
            rec = lines.next()
            if rec is None:
                raise lines.error(
                    f"file ends inside the epoch of line {first - 1} ({count} records announced)"
                )
            if self.lenient and rec[:1] == ">":
                lines.push_back(rec)
                raise lines.error(
                    f"epoch line announces {count} records, the next epoch line (line "
                    f"{first + len(body)}) follows after {len(body)}",
                    first - 1,
                )
            body.append(rec)
        return body

    def _epoch_line(self, line: str, lines: _Lines) -> tuple[int, int, tuple[int, float] | None]:
        """(flag, record count, GPST (week, tow) or None for a blank event time)."""
        try:
            flag = int(line[31:32])
            count = int(line[32:35])
            if count < 0:
                raise ValueError(f"flag {flag}, count {count}")
            if flag in (2, 3, 4) and not line[2:29].strip():
                return flag, count, None
            day = dt.date(int(line[2:6]), int(line[7:9]), int(line[10:12]))
            sod = int(line[13:15]) * 3600 + int(line[16:18]) * 60 + float(line[18:29])
            if not 0.0 <= sod < 86401.0:
                raise ValueError(f"time of day {sod} s")
            when = self._to_gpst(day.toordinal() - _GPS_EPOCH_ORDINAL, sod)
        except (ValueError, OverflowError) as exc:  # OverflowError: GLO time near year 1
            raise lines.error(f"bad epoch line {line.rstrip()!r}: {exc}") from exc
        return flag, count, when

    def _unknown_flag(
        self, flag: int, body: list[str], lineno: int, counters: Counter[str]
    ) -> None:
        """An epoch flag RINEX 3 does not define (7-9): its announced records are skipped
        with the epoch, with a warning, in a strict reader as in a lenient one (what it
        means is unknown, the file's framing is not broken)."""
        counters["epochs_skipped"] += 1
        log.warning(
            "%s:%d: epoch flag %d (RINEX 3 defines 0-6); epoch and its %d records skipped",
            self.path,
            lineno,
            flag,
            len(body),
        )

    def _special(
        self,
        flag: int,
        body: list[str],
        first: int,
        types: dict[str, tuple[str, ...]],
        counters: Counter[str],
    ) -> None:
        """Event flags 2-5 (special records) and 6 (cycle-slip records)."""
        if flag == 6:
            counters["cycle_slip_records"] += len(body)
            return
        counters[f"event_flag_{flag}"] += 1
        counters["special_records"] += len(body)
        if flag == 4:
            redefined = [
                (first + k, rec.rstrip("\r\n"))
                for k, rec in enumerate(body)
                if rec[60:80].strip() == "SYS / # / OBS TYPES"
            ]
            if redefined:
                types.update(_obs_types(redefined, self.path))
                log.info("%s:%d: observation types redefined in the data", self.path, first)

    def _epoch(
        self,
        when: tuple[int, float],
        body: list[str],
        first: int,
        cols: dict[str, _Columns],
        lines: _Lines,
    ) -> MeasurementEpoch:
        prn: list[str] = []
        sig: list[str] = []
        pr: list[float] = []
        cn0: list[float] = []
        dop: list[float] = []
        for k, rec in enumerate(body):
            head = rec[:1]
            col = cols.get(head)
            if col is None:
                if head == ">" or not head.strip():
                    raise lines.error(
                        f"expected an observation record, got {rec.rstrip()[:40]!r} "
                        "(fewer records than the epoch line announced?)",
                        first + k,
                    )
                continue
            i_pr, i_cn0, i_dop = col.pr, col.cn0, col.doppler
            without = "bds_without_b1i" if head == _READ else f"{head}_without_signal"
            if i_pr is None:
                self.counters[without] += 1
                continue
            try:
                value = _float(rec[i_pr : i_pr + 14])
                if not value > 0.0:  # blank (NaN) or zero: no pseudorange of the signal
                    self.counters[without] += 1
                    continue
                if not math.isfinite(value):
                    raise ValueError(f"pseudorange {value}")
                sat = _sat_id(rec[:3])
                c = math.nan if i_cn0 is None else _float(rec[i_cn0 : i_cn0 + 14])
                d = math.nan if i_dop is None else _float(rec[i_dop : i_dop + 14])
            except ValueError as exc:
                err = lines.error(f"bad observation record {rec[:3]!r}: {exc}", first + k)
                if not self.lenient:
                    raise err from exc
                self.counters["records_skipped"] += 1
                log.warning("%s; record skipped", err)
                continue
            prn.append(sat)
            sig.append(col.code or "2I")
            pr.append(value)
            cn0.append(c)
            dop.append(d)
        epoch = MeasurementEpoch.from_columns(
            when[0],
            when[1],
            prn,
            sig,
            np.array(pr, dtype=float),
            cn0_dbhz=cn0,
            doppler_hz=dop,
            source="rinex",
        )
        if len(epoch) < len(prn):
            if not self.counters["duplicate_records"]:
                log.warning(
                    "%s:%d: a satellite's record repeated in the epoch: the first kept, "
                    "later ones dropped (counted duplicate_records)",
                    self.path,
                    first - 1,
                )
            self.counters["duplicate_records"] += len(prn) - len(epoch)
        n_bds = sum(p[:1] == _READ for p in epoch.prn)
        self.counters["bds_measurements"] += n_bds
        if n_bds < len(epoch):
            for p in epoch.prn:
                if p[:1] != _READ:
                    self.counters[f"{p[:1]}_measurements"] += 1
        return epoch


def iter_obs(path: str | Path) -> Iterator[MeasurementEpoch]:
    """BDS B1I epochs of a RINEX 3 observation file (a generator; see RinexObsReader)."""
    return iter(RinexObsReader(path))


@dataclass(frozen=True, slots=True)
class NavData:
    """BDS content of one or more RINEX 3 navigation files.

    ``ephemerides`` maps ``"C06"`` to its sets sorted by (week, toe); ``leap_seconds`` is
    GPST - UTC [s] (a BDS ``LEAP SECONDS`` record, BDT - UTC, is converted by +14 s);
    ``counters`` counts records read and skipped per system.
    """

    version: float
    ephemerides: dict[str, tuple[Ephemeris, ...]]
    iono_bds: KlobucharParams | None = None
    iono_gps: KlobucharParams | None = None
    leap_seconds: int | None = None
    counters: dict[str, int] = field(default_factory=dict)
    ggto: TimeOffset | None = None
    """GST - GPST of the header's ``TIME SYSTEM CORR`` ``GAGP`` record, when it has one."""


def _iono(
    lines: list[tuple[int, str]], a: str, b: str, system: Literal["BDS", "GPS"], path: Path
) -> KlobucharParams | None:
    """Klobuchar alpha/beta from ``IONOSPHERIC CORR`` records (A4,1X,4D12.4)."""
    vals: dict[str, tuple[float, float, float, float]] = {}
    for lineno, text in lines:
        key = text[:4].strip()
        if key in (a, b) and key not in vals:
            try:
                v = [_float(text[5 + 12 * i : 17 + 12 * i]) for i in range(4)]
            except ValueError as exc:
                raise FramingError(f"{path}:{lineno}: bad IONOSPHERIC CORR: {exc}") from exc
            if any(math.isnan(x) for x in v):
                raise FramingError(f"{path}:{lineno}: IONOSPHERIC CORR {key} has blank fields")
            vals[key] = (v[0], v[1], v[2], v[3])
    if a in vals and b in vals:
        # the header prints broadcast values to 4-5 digits: back on their LSBs, as decoded
        return klobuchar_on_grid(KlobucharParams(alpha=vals[a], beta=vals[b], system=system))
    return None


def _ggto(lines: list[tuple[int, str]], path: Path) -> TimeOffset | None:
    """GST - GPST from a ``TIME SYSTEM CORR`` ``GAGP`` record (RINEX 3.04 Table A5:
    A4,1X,D17.10,D16.9,1X,I6,1X,I4: a0 [s], a1 [s/s], reference time [s of week] and week,
    the Galileo week counted as the GPS week); the GGTO of OS SIS ICD 5.1.8. It is only
    recorded (never applied), so an unreadable record is logged and skipped (None) rather
    than refusing the file's ephemerides."""
    for lineno, text in lines:
        if text[:4] != "GAGP":
            continue
        try:
            a0, a1 = _float(text[5:22]), _float(text[22:38])
            t_ref, week = int(text[38:45]), int(text[45:50])
        except ValueError as exc:
            log.warning("%s:%d: unreadable TIME SYSTEM CORR GAGP skipped: %s", path, lineno, exc)
            return None
        if math.isnan(a0) or math.isnan(a1):
            log.warning("%s:%d: TIME SYSTEM CORR GAGP has blank fields: skipped", path, lineno)
            return None
        return TimeOffset("GAGP", a0, a1, float(t_ref), week, "rinex")
    return None


def _leap_seconds(h: _Header, path: Path) -> int | None:
    """GPST - UTC from ``LEAP SECONDS`` (4I6,A3). A BDS record (identifier ``BDS``, or blank
    in a BDS-only file, as 3.02 writers do) holds BDT - UTC."""
    line = h.first("LEAP SECONDS")
    if line is None:
        return None
    try:
        value = int(line[:6])
    except ValueError:
        log.warning("%s: unreadable LEAP SECONDS %r", path, line[:24])
        return None
    ident = line[24:27].strip()
    if ident == "BDS" or (not ident and h.system == GnssSystem.BDS):
        return value + round(BDT_GPST_OFFSET_S)
    return value


def _nav_ephemeris(prn: str, rec: list[str], path: Path, lineno: int) -> tuple[Ephemeris, int]:
    """One BDS, GPS or Galileo navigation record (``_RECORDS`` layouts) as an Ephemeris on
    BDT (:class:`~service.core.types.Ephemeris`), with its rank among sets of the same t_oe
    (Galileo: I/NAV 1, F/NAV 0; others 1).

    BDS records are on BDT already. A GPS record's toc epoch, GPS week and toe are GPST
    (IS-GPS-200 20.3.3.4.3), a Galileo record's are GST with the GAL week counted as the GPS
    week (RINEX 3.04 Table A8); both go to BDT by GPST - 14 s (BDS-SIS-ICD-B1I-3.0 4.2,
    GST = GPST to tens of ns, OS SIS ICD 5.1.8). A Galileo set's group delay is BGD(E1,E5b)
    for an I/NAV set and BGD(E1,E5a) for an F/NAV one (OS SIS ICD 5.1.5: the delay that
    goes with the set's clock for an E1 user); GPS's is T_GD (IS-GPS-200 20.3.3.3.3.2).

    A blank required field or a non-finite integer field is a FramingError. A float field
    that reads as NaN or infinity (``NaN``, an exponent past the double range) is passed on
    as it is: judging values is the store's job (service.core.ephemeris.ephemeris_problem), and
    it refuses that one set while the rest of the file stays usable.
    """
    system = prn[0]
    name_of = _SYSTEM_NAMES[GnssSystem(system)]
    first = rec[0]
    values: dict[str, float] = {}
    blank: set[str] = set()
    k = 0
    try:
        day = dt.date(int(first[4:8]), int(first[9:11]), int(first[12:14]))
        sod = int(first[15:17]) * 3600 + int(first[18:20]) * 60 + int(first[21:23])
        if system == GnssSystem.BDS:
            toc_sow = float((day.toordinal() - _BDT_EPOCH_ORDINAL) % 7 * 86400 + sod)
        else:
            toc_gps_week, dow = divmod(day.toordinal() - _GPS_EPOCH_ORDINAL, 7)
            toc_sow = gpst_to_bdt(toc_gps_week, dow * 86400 + sod)[1]
        for k, fields in _FIELD_COLUMNS[system]:
            # the D exponents of a line read as E in one pass, so that ``float`` takes each
            # field at the first try (the number is the same; _float's second look, once a
            # field, was half of reading a nav file); anything else goes to _float as written
            line = rec[k]
            read = line.replace("D", "E").replace("d", "e")
            for name, a, b in fields:
                try:
                    values[name] = float(read[a:b])
                except ValueError:
                    text = line[a:b]
                    values[name] = _float(text)
                    if not text.strip():
                        blank.add(name)
    except ValueError as exc:
        raise FramingError(f"{path}:{lineno + k}: bad {name_of} record for {prn}: {exc}") from exc
    kwargs: dict[str, float | int] = {}
    if not blank:  # the usual record: every field written; only the integers to check
        kwargs.update(values)
        for name in _INT_FIELDS_OF[system]:
            value = values[name]
            if not math.isfinite(value):
                raise FramingError(
                    f"{path}:{lineno}: {name_of} record for {prn}: {name} is {value}"
                )
            kwargs[name] = int(value)
    else:
        for name, value in values.items():
            if name in blank:
                if name not in _OPTIONAL and name != "tot_sow_s":
                    raise FramingError(f"{path}:{lineno}: {name_of} record for {prn} lacks {name}")
                if name == "tot_sow_s":
                    continue
                value = _OPTIONAL[name]
            elif name in _INT_FIELDS and not math.isfinite(value):
                raise FramingError(
                    f"{path}:{lineno}: {name_of} record for {prn}: {name} is {value}"
                )
            kwargs[name] = int(value) if name in _INT_FIELDS else value
    kwargs.pop("tot_sow_s", None)
    rank = 1
    if system == GnssSystem.GAL:
        inav = bool(int(kwargs.pop("data_sources")) & _GAL_INAV)
        e5a, e5b = kwargs.pop("bgd_e5a_s"), kwargs.pop("bgd_e5b_s")
        kwargs["tgd1_s"], kwargs["tgd2_s"] = (e5b, e5a) if inav else (e5a, e5b)
        rank = int(inav)
    if system != GnssSystem.BDS:  # (a t_oe outside the week stays as read: the store refuses it)
        kwargs["week"], kwargs["toe_sow_s"] = toe_gpst_to_bdt(
            int(kwargs["week"]), kwargs["toe_sow_s"]
        )
    eph = Ephemeris(prn=prn, toc_sow_s=float(toc_sow), source="rinex", **kwargs)  # type: ignore[arg-type]
    return eph, rank


NTRIP_NAV_HERE = (
    "nav: a URL is no nav file; an NTRIP source (ntrip://...) is read by 'bdsfix run' (its "
    "'nav' key); here give a RINEX nav file"
)
"""The error (no URL in it: it may hold credentials) for a URL given as a nav file."""


_NAV4_EPH: dict[str, frozenset[str]] = {
    GnssSystem.GPS: frozenset({"LNAV"}),
    GnssSystem.GAL: frozenset({"INAV", "FNAV"}),
    GnssSystem.BDS: frozenset({"D1", "D2"}),
    GnssSystem.QZS: frozenset({"LNAV"}),
    GnssSystem.IRN: frozenset({"LNAV"}),
    GnssSystem.SBAS: frozenset({"SBAS"}),
    GnssSystem.GLO: frozenset({"FDMA"}),
}
"""RINEX 4 ephemeris message types whose data record is the RINEX 3 record of the system
(4.00, section 5.4 and the per-message tables of the navigation appendix): GPS/QZSS/NavIC
LNAV, Galileo I/NAV and F/NAV, BeiDou D1 and D2, SBAS, GLONASS FDMA. The others (CNAV,
CNV1-3, L1NV ...) have other layouts and are skipped, counted."""
_NAV4_TYPES = frozenset({"EPH", "STO", "EOP", "ION"})
"""The record types of a RINEX 4 navigation file (4.00 section 5.4)."""
_NAV4_KLOBUCHAR: dict[tuple[str, str], Literal["BDS", "GPS"]] = {
    ("C", "D1D2"): "BDS",
    ("G", "LNAV"): "GPS",
}
"""RINEX 4 ``ION`` records read: the Klobuchar coefficients BeiDou D1/D2 and GPS LNAV
broadcast (the navigation appendix's Klobuchar table)."""


def _nav4_records(
    body: list[str],
    base: int,
    path: Path,
    take: Callable[[list[str], int], None],
    counters: Counter[str],
    read: frozenset[str],
) -> dict[str, KlobucharParams]:
    """Walk the records of a RINEX 4 navigation file (4.00 section 5.4): each opens with a
    line ``> TYPE SV MSG`` (``EPH``, ``STO``, ``EOP``, ``ION``; SV the satellite that sent
    it, of which only the system letter is read; MSG the message type; 4.02 may add a
    subtype) and runs to the next such line. An ``EPH`` record of a type of
    :data:`_NAV4_EPH` is a RINEX 3 record, handed to ``take``; the Klobuchar ``ION``
    records of :data:`_NAV4_KLOBUCHAR` give the first set of each system; every other
    record is counted (``records4_<TYPE>_<system>_<MSG>``, the ION records read too) and
    skipped.
    A FramingError (``<file>:<line>``) for lines before the first ``>``, a ``>`` line that
    is no ``> TYPE SV MSG`` of the four types, and an ``EPH`` record whose first data line
    is not of its satellite (a line lost, a damaged ``>`` line), where either system is in
    ``read``; of other systems that is a warning, counted ``records_<system>_odd_length``."""
    iono: dict[str, KlobucharParams] = {}
    i, n_body = 0, len(body)
    while i < n_body:
        line = body[i]
        i += 1
        if not line.strip():
            counters["blank_lines"] += 1
            continue
        start = base + i
        if not line.startswith(">"):
            raise FramingError(
                f"{path}:{start}: expected a RINEX 4 record line '> TYPE SV MSG', got "
                f"{line.rstrip()[:40]!r}"
            )
        head = line[1:].split()
        end = i
        while end < n_body and not body[end].startswith(">"):
            end += 1
        rec = body[i:end]
        i = end
        while rec and not rec[-1].strip():
            rec.pop()
        if len(head) < 3 or head[0] not in _NAV4_TYPES:
            raise FramingError(f"{path}:{start}: bad RINEX 4 record line {line.rstrip()!r}")
        kind, sv, msg = head[:3]
        system = sv[:1]
        if kind == "EPH":
            data_sv = _sat_id(rec[0][:3]) if rec and rec[0][:1].strip() else ""
            if data_sv != _sat_id(sv):  # a line lost, or the '>' line of another record
                why = f"{path}:{start}: RINEX 4 {sv} {msg} record without its data line for {sv}"
                if system in read or data_sv[:1] in read:
                    raise FramingError(why)
                counters[f"records_{system}_odd_length"] += 1
                log.warning("%s", why)
                continue
            if msg in _NAV4_EPH.get(system, frozenset()):
                take(rec, start + 1)
                continue
        if kind == "ION" and (system, msg) in _NAV4_KLOBUCHAR:
            name = _NAV4_KLOBUCHAR[(system, msg)]
            if name not in iono:
                got = _klobuchar4(rec, name, path, start + 1)
                if got is not None:
                    iono[name] = got
            counters[f"records4_ION_{system}_{msg}"] += 1
            continue
        counters[f"records4_{kind}_{system}_{msg}"] += 1
    return iono


def _klobuchar4(
    rec: list[str], system: Literal["BDS", "GPS"], path: Path, lineno: int
) -> KlobucharParams | None:
    """alpha0-3 and beta0-3 of a RINEX 4 Klobuchar ``ION`` record: its first line holds
    the transmission epoch in columns 1-23 then three D19.12 fields, the next lines four
    after 4 blanks (the navigation appendix's Klobuchar table); the eight coefficients are
    its first eight fields. An unreadable record is logged and skipped (None): the
    ephemerides stay usable."""
    fields = [rec[0][23:42], rec[0][42:61], rec[0][61:80]] if rec else []
    for text in rec[1:]:
        fields += [text[4 + 19 * k : 23 + 19 * k] for k in range(4)]
    try:
        v = [_float(f) for f in fields[:8]]
    except ValueError:
        v = []
    if len(v) < 8 or any(math.isnan(x) for x in v):
        log.warning("%s:%d: unreadable %s Klobuchar ION record skipped", path, lineno, system)
        return None
    alpha, beta = (v[0], v[1], v[2], v[3]), (v[4], v[5], v[6], v[7])
    return klobuchar_on_grid(KlobucharParams(alpha=alpha, beta=beta, system=system))


def read_nav(path: str | Path, systems: Iterable[str] = (_READ,)) -> NavData:
    """The ephemerides of ``systems`` (RINEX letters among BDS, GPS and Galileo; BeiDou alone
    by default), on BDT (see :func:`_nav_ephemeris`), and the ionosphere coefficients of a
    RINEX 3 or 4 nav file (mixed or of one system; RINEX 4: :func:`_nav4_records`).

    Records of other systems are skipped (counted in ``counters``). When the same set
    (PRN, week, toe) appears more than once, a Galileo I/NAV set wins over an F/NAV one
    (bdsfix ranges on E1), then the latest transmission time, so a health change broadcast
    later is kept.
    """
    if looks_like_url(str(path)):  # ntrip://, ntrips://, http://... (a Path folds the "//")
        raise ConfigError(NTRIP_NAV_HERE)
    path = Path(path)
    read = frozenset(systems) & frozenset(_RECORDS)
    counters: Counter[str] = Counter()
    with _open(path) as fh:
        lines = _Lines(fh, path)
        h = _read_header(lines, "N")
        record_lines = dict(_NAV_RECORD_LINES)
        if h.version >= 3.05:
            record_lines[GnssSystem.GLO] = 5
        held: dict[str, dict[tuple[int, float], tuple[tuple[int, float], Ephemeris]]] = {}

        def take(rec: list[str], start: int) -> None:
            """One navigation record (its lines, trailing blank ones dropped; ``start``: the
            file's line of its first): counted, and kept when of a system read."""
            line = rec[0]
            sys_char = line[0]
            want = record_lines[sys_char]
            if len(rec) != want:
                if sys_char in read:
                    raise FramingError(
                        f"{path}:{start}: {_SYSTEM_NAMES[GnssSystem(sys_char)]} record "
                        f"{line[:3]!r} has {len(rec)} lines, expected {want}"
                    )
                counters[f"records_{sys_char}_odd_length"] += 1
                log.warning(
                    "%s:%d: %s record has %d lines, expected %d",
                    path,
                    start,
                    sys_char,
                    len(rec),
                    want,
                )
            counters[f"records_{sys_char}"] += 1
            if sys_char not in read:
                return
            prn = _sat_id(line[:3])
            eph, rank = _nav_ephemeris(prn, rec, path, start)
            tot = _float(rec[7][4:23])
            tot = -math.inf if math.isnan(tot) else tot
            key = (eph.week, eph.toe_sow_s)
            sets = held.setdefault(prn, {})
            if key in sets:
                counters[f"{_SYSTEM_NAMES[GnssSystem(sys_char)].lower()}_repeated_sets"] += 1
            if key not in sets or (rank, tot) >= sets[key][0]:
                sets[key] = ((rank, tot), eph)

        # the records as one list, walked by index (line k of ``body`` is line base + k + 1
        # of the file): a day's mixed nav file is ~7,000 lines, most of them of systems not
        # read, and a method call per line was a third of reading it
        body = lines.rest()
        base = lines.n
        if h.version >= 4.0:
            iono4 = _nav4_records(body, base, path, take, counters, read)
        else:
            iono4 = {}
            i, n_body = 0, len(body)
            while i < n_body:
                line = body[i]
                i += 1
                if not line.strip():
                    counters["blank_lines"] += 1
                    continue
                start = base + i
                if line[0] not in record_lines:
                    raise lines.error(
                        f"expected a navigation record, got {line.rstrip()[:40]!r}", start
                    )
                end = i
                while end < n_body and body[end][:1] in (" ", "\n", "\r"):
                    end += 1
                rec = body[i - 1 : end]
                i = end
                while len(rec) > 1 and not rec[-1].strip():
                    rec.pop()  # trailing blank lines belong to no record
                take(rec, start)
    return NavData(
        version=h.version,
        ephemerides={
            p: tuple(e for _, (_, e) in sorted(d.items())) for p, d in sorted(held.items())
        },
        iono_bds=iono4.get("BDS")
        or _iono(h.records.get("IONOSPHERIC CORR", []), "BDSA", "BDSB", "BDS", path),
        iono_gps=iono4.get("GPS")
        or _iono(h.records.get("IONOSPHERIC CORR", []), "GPSA", "GPSB", "GPS", path),
        leap_seconds=_leap_seconds(h, path),
        counters=dict(counters),
        ggto=_ggto(h.records.get("TIME SYSTEM CORR", []), path),
    )


def merge_nav(*navs: NavData) -> NavData:
    """Union of several nav files' BDS content.

    A set (PRN, week, toe) present in several files is taken from the first file that has
    it; ionosphere coefficients and leap seconds come from the first file that has them.
    """
    if not navs:
        raise ValueError("merge_nav needs at least one NavData")
    ephs: dict[str, dict[tuple[int, float], Ephemeris]] = {}
    counters: Counter[str] = Counter()
    for nav in navs:
        counters.update(nav.counters)
        for prn, items in nav.ephemerides.items():
            for e in items:
                ephs.setdefault(prn, {}).setdefault((e.week, e.toe_sow_s), e)
    return NavData(
        version=max(n.version for n in navs),
        ephemerides={p: tuple(e for _, e in sorted(d.items())) for p, d in sorted(ephs.items())},
        iono_bds=next((n.iono_bds for n in navs if n.iono_bds), None),
        iono_gps=next((n.iono_gps for n in navs if n.iono_gps), None),
        leap_seconds=next((n.leap_seconds for n in navs if n.leap_seconds is not None), None),
        counters=dict(counters),
        ggto=next((n.ggto for n in navs if n.ggto is not None), None),
    )


__all__ = [
    "NavData",
    "ObsHeader",
    "RinexObsReader",
    "iter_obs",
    "merge_nav",
    "read_nav",
]


def detect(path: Path, head: bytes) -> bool:
    """True when the file's first line carries the RINEX header label (also gzip, Unix
    compress and Hatanaka compact RINEX: :func:`open_text`). The registry's detection
    (:data:`drivers.protocols.FILE_FORMATS`); a nav file is detected too, and refused by
    the obs reader's header check."""
    first = head.split(b"\n", 1)[0][:200]
    if b"RINEX VERSION / TYPE" in first or b"CRINEX VERS" in first:
        return True
    if not first.startswith(COMPRESSED_MAGICS):
        return False
    try:
        with open_text(path) as fh:
            return "RINEX VERSION / TYPE" in fh.readline(200)
    except FramingError:
        return False


def obs_events(
    path: str | Path,
    counters: Counter[str] | None = None,
    lenient: bool = True,
    systems: Iterable[str] = (_READ,),
) -> Iterator[MeasurementEpoch]:
    """The epochs of the obs file at ``path`` (:class:`RinexObsReader`) with the satellites
    of ``systems``, counting ``epochs_rinex`` and the reader's skipped records into
    ``counters``.
    The header is read now (a bad one raises here, not at the first epoch); the file is
    closed when the iteration ends or is closed. The registry's reader."""
    reader = RinexObsReader(path, lenient=lenient, systems=systems)
    if counters is not None:
        reader.counters = counters  # one set: the reader's skipped epochs reach STATUS
    return _counted(reader, reader.counters)


def _counted(reader: RinexObsReader, counters: Counter[str]) -> Iterator[MeasurementEpoch]:
    try:
        for epoch in reader:
            counters["epochs_rinex"] += 1
            yield epoch
    finally:
        reader.close()
