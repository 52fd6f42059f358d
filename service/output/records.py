"""The one place that turns results into the JSON/CSV contract of docs/architecture.md.

Every record is a flat JSON object with a ``class`` (``FIX``, ``SKY``, ``TRACK``,
``STATUS``); on ZeroMQ the class is also the topic. :data:`SCHEMAS` holds a JSON Schema
(draft 2020-12) for each class, plain JSON data (the tests check records against it with
jsonschema).

Field rules, common to all classes:

- fields that do not apply are omitted, never ``null``; non-finite numbers (NaN, inf) are
  omitted too, so every line is strict JSON (``allow_nan=False``);
- times are GPST ``gpst_week`` (int) and ``gpst_tow_s`` (s, 1 µs resolution);
  ``since_start_s`` is data time since the stream's first measurement (or since an
  emulated restart) and appears on records from a stream only;
- precision: ``x_ecef_m`` 0.1 mm, ``lat_deg``/``lon_deg`` 1e-10 deg (~0.01 mm),
  ``alt_m``/``clock_bias_m``/``resid_rms_m`` 0.1 mm, DOPs 0.001.

``FIX`` (one per epoch and solver; ``solver`` is which ran, ``mode`` what it achieved):
  always ``class solver mode gpst_week gpst_tow_s n_full n_frac``, except that a fix
  declined because no GPS week is known yet (``reason_code`` ``no_time``) has no
  ``gpst_week`` (its ``gpst_tow_s`` is the source's time of week);
  with a position (mode ``fast``/``spp``): ``x_ecef_m lat_deg lon_deg alt_m clock_bias_m``,
  and ``clocks_m`` {system letter: receiver clock [m], 0.1 mm} and ``used_by_system``
  {letter: satellites used} when the rows came from more than one satellite system (each
  system's clock, :attr:`Fix.clocks_m`; ``clock_bias_m`` is then BeiDou's clock, or the
  first system's; a one-system fix has only ``clock_bias_m``), and, when computed,
  ``pdop resid_rms_m``; ``gdop_full`` when the solver computed it (the fast solver, also
  on a GDOP-gate decline); ``ambiguity`` {PRN: integer N of
  eq. (13)} when not empty, which is the fast solver's fractional satellites (also on a
  fast fix declined by the chi-square test, for diagnosis); ``reason`` (and a
  ``reason_code``, one of :class:`service.core.declines.Decline`) exactly when ``mode`` is
  ``none`` (a declined fix has no position fields).
  Integrity (:mod:`service.engine.raim`): ``redundancy`` (rows - unknowns of the layout:
  used satellites - 4 for a BeiDou-only fix) once a solution was judged, with ``chi2``
  and its threshold ``chi2_max`` when it is >= 1; on a fix, ``raim`` (``pass``,
  ``unprotected`` or ``untested``, see :func:`raim_state`), the protection levels
  ``hpl_m``/``vpl_m`` when finite, ``std_enu_m`` (1-sigma east, north, up from the
  solution covariance); ``excluded`` {PRN: why} when fault exclusion (or an
  impossible range) removed satellites; they are not in the fix.
  Velocity (:mod:`service.engine.velocity`, from the epoch's Doppler), on a fix whose
  Doppler rows passed their residual test, all together: ``v_enu_m_s`` (east, north, up),
  ``speed_m_s`` (horizontal, over ground), ``course_deg`` (clockwise from true north, in
  [0, 360)), ``clock_drift_m_s`` (c times the receiver clock rate), each with its 1-sigma
  ``std_v_enu_m_s``, ``std_speed_m_s``, ``std_course_deg`` (at most 180),
  ``std_clock_drift_m_s``; precision 0.1 mm/s and 0.01 deg.
  ``receiver_fix`` (when the source carries the receiver's own fix: an Android ``Fix,``
  row, a Septentrio PVTGeodetic; the latest one within 1.5 s of the epoch): ``source``
  (``android-<provider>``, ``sbf-pvtgeodetic``), its ``gpst_tow_s`` and ``age_s`` (epoch
  minus receiver fix time), ``lat_deg lon_deg`` and when given ``alt_m`` (ellipsoidal)
  and ``accuracy_m`` (the receiver's own estimate); on a fix with a position ``dist_m``,
  the 3-D distance between the two.
  A fast fix made by the coarse-time method (:mod:`service.engine.coarse`, fewer than four
  full ranges) says so: ``method`` ``coarse_time`` and ``time_offset_s``, the solved error
  of the epoch's time tag (true receive time = tag + offset, 1 µs resolution); the paper's
  fast fix and SPP carry neither.
``SKY``: ``class gpst_week gpst_tow_s satellites``; each satellite ``prn el_deg az_deg
  used full signal`` plus ``cn0_dbhz`` when measured.
``TRACK`` (a satellite's frame-sync event): ``class prn event nav_type gpst_week
  gpst_tow_s since_start_s``; ``prn`` a RINEX 3 satellite ID (BeiDou, or GPS/Galileo from a
  multi-system source such as a phone log), ``nav_type`` ``D2`` for a BeiDou GEO, ``D1``
  for every other BeiDou satellite, ``LNAV`` for GPS and ``INAV`` for Galileo; ``event`` is
  ``sow`` (a subframe's SOW decoded: ``sow_s`` is the BDT second of week at which that
  subframe started) or ``full`` (its measurement became a full pseudorange at ``gpst_tow_s``);
  ``full_since_s`` (data time since the stream start at which it first became full) when
  the caller knows it.
``STATUS``: ``class counters`` ({name: number}) plus any scalar extras the caller adds
  (e.g. ``uptime_s``).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from service.core.declines import NO_REASON
from service.core.geometry import geodetic_to_ecef
from service.core.timebase import diff_s
from service.core.types import UNKNOWN_WEEK, Fix, ReceiverFix, SatView, Velocity

CSV_COLUMNS = (
    "solver",
    "mode",
    "gpst_week",
    "gpst_tow_s",
    "x_ecef_m",
    "y_ecef_m",
    "z_ecef_m",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "clock_bias_m",
    "gdop_full",
    "pdop",
    "n_full",
    "n_frac",
    "resid_rms_m",
    "reason",
    "redundancy",
    "hpl_m",
    "vpl_m",
    "v_east_m_s",
    "v_north_m_s",
    "v_up_m_s",
    "speed_m_s",
    "course_deg",
    "clock_drift_m_s",
)

TRACK_EVENTS = ("sow", "full")


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _put(rec: dict[str, Any], key: str, value: float | None, ndigits: int) -> None:
    """Set ``rec[key]`` to ``value`` rounded, unless it is None or not finite."""
    if _finite(value):
        rec[key] = round(float(value), ndigits)  # type: ignore[arg-type]


def receiver_fix_record(rf: ReceiverFix, fix: Fix) -> dict[str, Any]:
    """The ``receiver_fix`` object of a FIX record: the receiver's own fix, its age at the
    epoch, and on a fix with a position the distance between the two."""
    rec: dict[str, Any] = {"source": rf.source, "gpst_tow_s": round(float(rf.gpst_tow_s), 6)}
    _put(rec, "age_s", diff_s(fix.gpst_week, fix.gpst_tow_s, rf.gpst_week, rf.gpst_tow_s), 6)
    _put(rec, "lat_deg", rf.lat_deg, 10)
    _put(rec, "lon_deg", rf.lon_deg, 10)
    _put(rec, "alt_m", rf.alt_m, 4)
    _put(rec, "accuracy_m", rf.accuracy_m, 4)
    if fix.ok and fix.x_ecef_m is not None and _finite(rf.alt_m):
        theirs = geodetic_to_ecef(math.radians(rf.lat_deg), math.radians(rf.lon_deg), rf.alt_m)
        _put(rec, "dist_m", float(np.linalg.norm(np.subtract(fix.x_ecef_m, theirs))), 4)
    return rec


def fix_record(
    fix: Fix, since_start_s: float | None = None, receiver_fix: ReceiverFix | None = None
) -> dict[str, Any]:
    """The ``FIX`` record of one solver at one epoch (field rules in the module docstring)."""
    rec: dict[str, Any] = {
        "class": "FIX",
        "solver": fix.solver,
        "mode": fix.mode,
        "gpst_week": int(fix.gpst_week),
        "gpst_tow_s": round(float(fix.gpst_tow_s), 6),
    }
    if fix.gpst_week == UNKNOWN_WEEK:
        del rec["gpst_week"]
    _put(rec, "since_start_s", since_start_s, 6)
    if fix.ok:
        if fix.x_ecef_m is not None and all(_finite(v) for v in fix.x_ecef_m):
            rec["x_ecef_m"] = [round(float(v), 4) for v in fix.x_ecef_m]
        _put(rec, "lat_deg", fix.lat_deg, 10)
        _put(rec, "lon_deg", fix.lon_deg, 10)
        _put(rec, "alt_m", fix.alt_m, 4)
        _put(rec, "clock_bias_m", fix.clock_bias_m, 4)
        if len(fix.clocks_m) > 1 and all(_finite(v) for v in fix.clocks_m.values()):
            rec["clocks_m"] = {k: round(float(v), 4) for k, v in sorted(fix.clocks_m.items())}
            used = Counter(p[:1] for p in fix.used)
            rec["used_by_system"] = {k: used[k] for k in rec["clocks_m"]}
    _put(rec, "gdop_full", fix.gdop_full, 3)
    if fix.ok:
        _put(rec, "pdop", fix.pdop, 3)
    rec["n_full"] = len(fix.full)
    rec["n_frac"] = len(fix.fractional)
    if fix.ambiguity:
        rec["ambiguity"] = {prn: int(n) for prn, n in sorted(fix.ambiguity.items())}
    _put(rec, "resid_rms_m", fix.resid_rms_m, 4)
    if fix.redundancy is not None:
        rec["redundancy"] = int(fix.redundancy)
    _put(rec, "chi2", fix.chi2, 3)
    _put(rec, "chi2_max", fix.chi2_max, 3)
    if fix.ok:
        rec["raim"] = raim_state(fix)
        _put(rec, "hpl_m", fix.hpl_m, 3)
        _put(rec, "vpl_m", fix.vpl_m, 3)
        if fix.std_enu_m is not None and all(_finite(v) for v in fix.std_enu_m):
            rec["std_enu_m"] = [round(float(v), 4) for v in fix.std_enu_m]
        if fix.velocity is not None:
            _put_velocity(rec, fix.velocity)
    if fix.ok and fix.method is not None:
        rec["method"] = fix.method
        _put(rec, "time_offset_s", fix.time_offset_s, 6)
    if fix.excluded:
        rec["excluded"] = dict(sorted(fix.excluded.items()))
    if not fix.ok:
        rec["reason"] = fix.reason or NO_REASON
        if fix.reason_code:
            rec["reason_code"] = fix.reason_code
    if receiver_fix is not None and fix.gpst_week != UNKNOWN_WEEK:
        rec["receiver_fix"] = receiver_fix_record(receiver_fix, fix)
    return rec


def _put_velocity(rec: dict[str, Any], vel: Velocity) -> None:
    """The velocity fields of a ``FIX`` record (all or none: every value must be finite)."""
    values = (
        *vel.v_enu_m_s,
        *vel.std_v_enu_m_s,
        vel.speed_m_s,
        vel.std_speed_m_s,
        vel.course_deg,
        vel.std_course_deg,
        vel.clock_drift_m_s,
        vel.std_clock_drift_m_s,
    )
    if not all(_finite(v) for v in values):
        return
    rec["v_enu_m_s"] = [round(float(v), 4) for v in vel.v_enu_m_s]
    rec["std_v_enu_m_s"] = [round(float(v), 4) for v in vel.std_v_enu_m_s]
    rec["speed_m_s"] = round(float(vel.speed_m_s), 4)
    rec["std_speed_m_s"] = round(float(vel.std_speed_m_s), 4)
    rec["course_deg"] = round(float(vel.course_deg), 2) % 360.0
    rec["std_course_deg"] = round(float(vel.std_course_deg), 2)
    rec["clock_drift_m_s"] = round(float(vel.clock_drift_m_s), 4)
    rec["std_clock_drift_m_s"] = round(float(vel.std_clock_drift_m_s), 4)


RAIM_STATES = ("pass", "unprotected", "untested")


def raim_state(fix: Fix) -> str:
    """Integrity of a published fix in one word: ``pass`` (the chi-square test passed and
    the protection levels bound a single fault), ``unprotected`` (it passed, but a
    satellite without redundancy makes the levels infinite), ``untested`` (redundancy 0:
    no test is possible)."""
    if fix.chi2 is None:
        return "untested"
    if not (_finite(fix.hpl_m) and _finite(fix.vpl_m)):
        return "unprotected"
    return "pass"


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
"""What ``json.dumps(rec, separators=(",", ":"), allow_nan=False)`` builds at each call."""


def dumps(rec: Mapping[str, Any]) -> str:
    """Compact one-line strict JSON (raises ValueError on NaN/inf)."""
    return _ENCODER.encode(rec)


def fix_json_line(fix: Fix, since_start_s: float | None = None) -> str:
    """One JSONL line (no newline) for ``bdsfix solve --format jsonl`` and the streams."""
    return dumps(fix_record(fix, since_start_s))


def csv_header() -> str:
    """The header line of ``--format csv`` (no newline)."""
    return ",".join(CSV_COLUMNS)


def fix_csv_row(fix: Fix) -> str:
    """One CSV row (no newline); cells that do not apply are empty; RFC 4180 quoting."""
    rec = fix_record(fix)
    x, y, z = rec.pop("x_ecef_m", ("", "", ""))
    ve, vn, vu = rec.pop("v_enu_m_s", ("", "", ""))
    rec |= {"x_ecef_m": x, "y_ecef_m": y, "z_ecef_m": z}
    rec |= {"v_east_m_s": ve, "v_north_m_s": vn, "v_up_m_s": vu}
    buf = io.StringIO()
    csv.writer(buf, lineterminator="").writerow([rec.get(col, "") for col in CSV_COLUMNS])
    return buf.getvalue()


def sky_record(gpst_week: int, gpst_tow_s: float, sats: Sequence[SatView]) -> dict[str, Any]:
    """The ``SKY`` record: satellites in view with elevation, azimuth, C/N0 and use."""
    out = []
    finite = math.isfinite
    for s in sats:  # (_put of each figure, written out: a few calls less per satellite)
        sat: dict[str, Any] = {"prn": s.prn}
        el, az, cn0 = s.el_deg, s.az_deg, s.cn0_dbhz
        if el is not None and finite(el):
            sat["el_deg"] = round(float(el), 2)
        if az is not None and finite(az):
            sat["az_deg"] = round(float(az), 2) % 360.0
        if cn0 is not None and finite(cn0):
            sat["cn0_dbhz"] = round(float(cn0), 1)
        sat["used"], sat["full"], sat["signal"] = bool(s.used), bool(s.full), s.signal
        out.append(sat)
    return {
        "class": "SKY",
        "gpst_week": int(gpst_week),
        "gpst_tow_s": round(float(gpst_tow_s), 6),
        "satellites": out,
    }


def track_record(
    prn: str,
    event: str,
    gpst_week: int,
    gpst_tow_s: float,
    since_start_s: float,
    nav_type: str,
    sow_s: float | None = None,
    full_since_s: float | None = None,
) -> dict[str, Any]:
    """The ``TRACK`` record of one frame-sync event (``sow`` or ``full``)."""
    rec: dict[str, Any] = {
        "class": "TRACK",
        "prn": prn,
        "event": event,
        "nav_type": nav_type,
        "gpst_week": int(gpst_week),
        "gpst_tow_s": round(float(gpst_tow_s), 6),
        "since_start_s": round(float(since_start_s), 6),
    }
    _put(rec, "sow_s", sow_s, 6)
    _put(rec, "full_since_s", full_since_s, 6)
    return rec


def track_record_of(event: Any) -> dict[str, Any]:
    """``TRACK`` record of a :class:`service.engine.tracker.TrackEvent` (or any look-alike)."""
    return track_record(
        event.prn,
        event.event,
        event.gpst_week,
        event.gpst_tow_s,
        event.since_start_s,
        event.nav_type,
        getattr(event, "sow_s", None),
        getattr(event, "full_since_s", None),
    )


def status_record(counters: Mapping[str, int | float], **extra: Any) -> dict[str, Any]:
    """The ``STATUS`` record: counters of every stage plus scalar extras (None/NaN omitted)."""
    rec: dict[str, Any] = {"class": "STATUS"}
    for key, value in extra.items():
        if key in ("class", "counters") or value is None:
            continue
        if isinstance(value, float) and not math.isfinite(value):
            continue
        rec[key] = value
    rec["counters"] = {
        k: (v if isinstance(v, float) else int(v))
        for k, v in sorted(counters.items())
        if math.isfinite(v)
    }
    return rec


# ---- JSON Schemas (draft 2020-12) ---------------------------------------------------------

_DIALECT = "https://json-schema.org/draft/2020-12/schema"
_NUM = {"type": "number"}
_NONNEG = {"type": "number", "minimum": 0}
_COUNT = {"type": "integer", "minimum": 0}
_PRN = {"type": "string", "pattern": "^[CGERJSI][0-9]{2}$"}
"""A RINEX 3 satellite ID: BeiDou, or another system's from a multi-system source (a phone
log's GPS and Galileo rows reach the tracker, ``TRACK``)."""
_WEEK = {"type": "integer", "minimum": 0}
_TOW = {"type": "number", "minimum": 0, "exclusiveMaximum": 604800}
_POSITION = ("x_ecef_m", "lat_deg", "lon_deg", "alt_m", "clock_bias_m")
_VELOCITY = (
    "v_enu_m_s",
    "std_v_enu_m_s",
    "speed_m_s",
    "std_speed_m_s",
    "course_deg",
    "std_course_deg",
    "clock_drift_m_s",
    "std_clock_drift_m_s",
)

SCHEMAS: dict[str, dict[str, Any]] = {
    "FIX": {
        "$schema": _DIALECT,
        "title": "bdsfix FIX",
        "type": "object",
        "required": ["class", "solver", "mode", "gpst_tow_s", "n_full", "n_frac"],
        "anyOf": [
            {"required": ["gpst_week"]},
            {"required": ["reason_code"], "properties": {"reason_code": {"const": "no_time"}}},
        ],
        "properties": {
            "class": {"const": "FIX"},
            "solver": {"enum": ["fast", "spp"]},
            "mode": {"enum": ["fast", "spp", "none"]},
            "gpst_week": _WEEK,
            "gpst_tow_s": _TOW,
            "since_start_s": _NUM,
            "x_ecef_m": {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3},
            "lat_deg": {"type": "number", "minimum": -90, "maximum": 90},
            "lon_deg": {"type": "number", "minimum": -180, "maximum": 180},
            "alt_m": _NUM,
            "clock_bias_m": _NUM,
            "clocks_m": {
                "type": "object",
                "minProperties": 2,
                "patternProperties": {"^[A-Z]$": _NUM},
                "additionalProperties": False,
            },
            "used_by_system": {
                "type": "object",
                "minProperties": 2,
                "patternProperties": {"^[A-Z]$": _COUNT},
                "additionalProperties": False,
            },
            "gdop_full": _NONNEG,
            "pdop": _NONNEG,
            "n_full": _COUNT,
            "n_frac": _COUNT,
            "ambiguity": {
                "type": "object",
                "minProperties": 1,
                "patternProperties": {"^[CGE][0-9]{2}$": {"type": "integer"}},
                "additionalProperties": False,
            },
            "resid_rms_m": _NONNEG,
            "redundancy": _COUNT,
            "chi2": _NONNEG,
            "chi2_max": _NONNEG,
            "raim": {"enum": list(RAIM_STATES)},
            "hpl_m": _NONNEG,
            "vpl_m": _NONNEG,
            "std_enu_m": {"type": "array", "items": _NONNEG, "minItems": 3, "maxItems": 3},
            "v_enu_m_s": {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3},
            "std_v_enu_m_s": {"type": "array", "items": _NONNEG, "minItems": 3, "maxItems": 3},
            "speed_m_s": _NONNEG,
            "std_speed_m_s": _NONNEG,
            "course_deg": {"type": "number", "minimum": 0, "exclusiveMaximum": 360},
            "std_course_deg": {"type": "number", "minimum": 0, "maximum": 180},
            "clock_drift_m_s": _NUM,
            "std_clock_drift_m_s": _NONNEG,
            "excluded": {
                "type": "object",
                "minProperties": 1,
                "patternProperties": {"^[CGE][0-9]{2}$": {"type": "string", "minLength": 1}},
                "additionalProperties": False,
            },
            "method": {"enum": ["coarse_time"]},
            "time_offset_s": _NUM,
            "reason": {"type": "string", "minLength": 1},
            "reason_code": {"type": "string", "minLength": 1},
            "receiver_fix": {
                "type": "object",
                "required": ["source", "gpst_tow_s", "age_s", "lat_deg", "lon_deg"],
                "properties": {
                    "source": {"type": "string", "minLength": 1},
                    "gpst_tow_s": _TOW,
                    "age_s": _NUM,
                    "lat_deg": {"type": "number", "minimum": -90, "maximum": 90},
                    "lon_deg": {"type": "number", "minimum": -180, "maximum": 180},
                    "alt_m": _NUM,
                    "accuracy_m": _NONNEG,
                    "dist_m": _NONNEG,
                },
                "additionalProperties": False,
            },
        },
        "additionalProperties": False,
        "if": {"properties": {"mode": {"const": "none"}}},
        "then": {
            "required": ["reason"],
            "not": {
                "anyOf": [
                    {"required": [k]}
                    for k in (*_POSITION, *_VELOCITY, "clocks_m", "pdop", "raim", "hpl_m", "vpl_m")
                ]
            },
        },
        "else": {
            "required": [*_POSITION, "raim"],
            "not": {"anyOf": [{"required": ["reason"]}, {"required": ["reason_code"]}]},
        },
        # the velocity fields come all together or not at all
        "dependentRequired": {k: list(_VELOCITY) for k in _VELOCITY},
    },
    "SKY": {
        "$schema": _DIALECT,
        "title": "bdsfix SKY",
        "type": "object",
        "required": ["class", "gpst_week", "gpst_tow_s", "satellites"],
        "properties": {
            "class": {"const": "SKY"},
            "gpst_week": _WEEK,
            "gpst_tow_s": _TOW,
            "satellites": {
                "type": "array",
                "items": {
                    "type": "object",
                    "required": ["prn", "used", "full"],
                    "properties": {
                        "prn": _PRN,
                        "el_deg": {"type": "number", "minimum": -90, "maximum": 90},
                        "az_deg": {"type": "number", "minimum": 0, "exclusiveMaximum": 360},
                        "cn0_dbhz": _NUM,
                        "used": {"type": "boolean"},
                        "full": {"type": "boolean"},
                        "signal": {"type": "string"},
                    },
                    "additionalProperties": False,
                },
            },
        },
        "additionalProperties": False,
    },
    "TRACK": {
        "$schema": _DIALECT,
        "title": "bdsfix TRACK",
        "type": "object",
        "required": [
            "class",
            "prn",
            "event",
            "nav_type",
            "gpst_week",
            "gpst_tow_s",
            "since_start_s",
        ],
        "properties": {
            "class": {"const": "TRACK"},
            "prn": _PRN,
            "event": {"enum": list(TRACK_EVENTS)},
            "nav_type": {"enum": ["D1", "D2", "LNAV", "INAV"]},
            "gpst_week": _WEEK,
            "gpst_tow_s": _TOW,
            "since_start_s": _NUM,
            "sow_s": {"type": "number", "minimum": 0, "exclusiveMaximum": 604800},
            "full_since_s": _NUM,
        },
        "additionalProperties": False,
        "if": {"properties": {"event": {"const": "sow"}}},
        "then": {"required": ["sow_s"]},
    },
    "STATUS": {
        "$schema": _DIALECT,
        "title": "bdsfix STATUS",
        "type": "object",
        "required": ["class", "counters"],
        "properties": {
            "class": {"const": "STATUS"},
            "counters": {"type": "object", "additionalProperties": _NUM},
        },
        "additionalProperties": {"type": ["string", "number", "boolean"]},
    },
}
