"""The one place that turns results into the JSON/CSV contract of ARCHITECTURE.md.

Field rules: fields that do not apply are omitted, never null; non-finite numbers are
omitted too, so every line is strict JSON. ``ambiguity`` and ``gdop_full`` appear on fast
solver records that have them; ``reason`` on records whose ``mode`` is ``none``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

from service.types import Fix, SatView

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
)


def _put(rec: dict[str, Any], key: str, value: float | None, ndigits: int | None = None) -> None:
    if value is None or not math.isfinite(value):
        return
    rec[key] = round(value, ndigits) if ndigits is not None else value


def fix_record(fix: Fix, since_start_s: float | None = None) -> dict[str, Any]:
    """The ``FIX`` record of one solver at one epoch."""
    rec: dict[str, Any] = {
        "class": "FIX",
        "solver": fix.solver,
        "mode": fix.mode,
        "gpst_week": fix.gpst_week,
        "gpst_tow_s": round(fix.gpst_tow_s, 6),
    }
    if since_start_s is not None:
        rec["since_start_s"] = round(since_start_s, 6)
    if fix.x_ecef_m is not None:
        rec["x_ecef_m"] = [round(v, 4) for v in fix.x_ecef_m]
    _put(rec, "lat_deg", fix.lat_deg, 10)
    _put(rec, "lon_deg", fix.lon_deg, 10)
    _put(rec, "alt_m", fix.alt_m, 4)
    _put(rec, "clock_bias_m", fix.clock_bias_m, 4)
    _put(rec, "gdop_full", fix.gdop_full, 3)
    _put(rec, "pdop", fix.pdop, 3)
    rec["n_full"] = len(fix.full)
    rec["n_frac"] = len(fix.fractional)
    if fix.ambiguity:
        rec["ambiguity"] = dict(sorted(fix.ambiguity.items()))
    _put(rec, "resid_rms_m", fix.resid_rms_m, 4)
    if fix.reason:
        rec["reason"] = fix.reason
    return rec


def dumps(rec: Mapping[str, Any]) -> str:
    """Compact one-line strict JSON."""
    return json.dumps(rec, separators=(",", ":"), allow_nan=False)


def fix_json_line(fix: Fix, since_start_s: float | None = None) -> str:
    return dumps(fix_record(fix, since_start_s))


def csv_header() -> str:
    return ",".join(CSV_COLUMNS)


def fix_csv_row(fix: Fix) -> str:
    rec = fix_record(fix)
    xyz = rec.pop("x_ecef_m", ["", "", ""])
    rec["x_ecef_m"], rec["y_ecef_m"], rec["z_ecef_m"] = xyz
    if "reason" in rec:
        rec["reason"] = '"' + str(rec["reason"]).replace('"', '""') + '"'
    return ",".join(str(rec.get(col, "")) for col in CSV_COLUMNS)


def sky_record(gpst_week: int, gpst_tow_s: float, sats: Sequence[SatView]) -> dict[str, Any]:
    """The ``SKY`` record: satellites in view with elevation, azimuth, C/N0 and use."""
    return {
        "class": "SKY",
        "gpst_week": gpst_week,
        "gpst_tow_s": round(gpst_tow_s, 6),
        "satellites": [
            {
                "prn": s.prn,
                "el_deg": round(s.el_deg, 2),
                "az_deg": round(s.az_deg, 2),
                **({"cn0_dbhz": s.cn0_dbhz} if math.isfinite(s.cn0_dbhz) else {}),
                "used": s.used,
                "full": s.full,
            }
            for s in sats
        ],
    }


def status_record(counters: Mapping[str, int | float], **extra: Any) -> dict[str, Any]:
    """The ``STATUS`` record: counters of every stage."""
    rec: dict[str, Any] = {"class": "STATUS", **extra}
    rec["counters"] = {k: v for k, v in sorted(counters.items()) if math.isfinite(v)}
    return rec
