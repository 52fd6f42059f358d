"""JSON/CSV records: the contract of docs/architecture.md, strict JSON, and the JSON Schemas
(checked with jsonschema) against hand-written good and bad records and against every golden
replay record."""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from service.core.declines import Decline, Declined
from service.core.types import SatView, Velocity
from service.output.records import (
    CSV_COLUMNS,
    SCHEMAS,
    csv_header,
    fix_csv_row,
    fix_json_line,
    fix_record,
    sky_record,
    status_record,
    track_record,
)
from tests.support.fixes import HKSC_ECEF_M, SKY, declined_fix, ecef_m, geodetic_deg_m, hksc_fix
from tests.support.paths import GOLDEN
from tests.support.schema import schema_errors, validate

# The FIX fields of docs/architecture.md, written out here, plus the stream field since_start_s.
CONTRACT_FIX_FIELDS = {
    "class",
    "solver",
    "mode",
    "gpst_week",
    "gpst_tow_s",
    "x_ecef_m",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "clock_bias_m",
    "gdop_full",
    "pdop",
    "n_full",
    "n_frac",
    "ambiguity",
    "resid_rms_m",
    "reason",
    "since_start_s",
    "redundancy",
    "chi2",
    "chi2_max",
    "raim",
    "hpl_m",
    "vpl_m",
    "std_enu_m",
}
CONDITIONAL_FIX_FIELDS = {
    "excluded",
    "reason_code",
    "clocks_m",
    "used_by_system",
    "receiver_fix",
    "method",
    "time_offset_s",
}
"""Fields present only when satellites were excluded / on a declined fix / on a fix from
rows of more than one satellite system / when the source carries the receiver's own fix /
on a fix of the coarse-time method."""
VELOCITY_FIX_FIELDS = {
    "v_enu_m_s",
    "std_v_enu_m_s",
    "speed_m_s",
    "std_speed_m_s",
    "course_deg",
    "std_course_deg",
    "clock_drift_m_s",
    "std_clock_drift_m_s",
}
"""Fields of a fix with a velocity from Doppler (all or none)."""


def strict_loads(line: str) -> object:
    def no_constants(name: str) -> object:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(line, parse_constant=no_constants)


def test_hksc_geodetic_helper_is_sane():
    lat, lon, h = geodetic_deg_m(*HKSC_ECEF_M)
    assert abs(lat - 22.3222) < 1e-3 and abs(lon - 114.1412) < 1e-3 and 0 < h < 60
    back = ecef_m(lat, lon, h)
    assert max(abs(a - b) for a, b in zip(back, HKSC_ECEF_M, strict=True)) < 1e-6


def test_fast_fix_record_follows_the_contract():
    fix = hksc_fix()
    rec = fix_record(fix, since_start_s=1.2)
    assert set(rec) == CONTRACT_FIX_FIELDS - {"reason"}
    assert rec["class"] == "FIX" and rec["solver"] == rec["mode"] == "fast"
    assert rec["gpst_week"] == 2161 and isinstance(rec["gpst_week"], int)
    assert rec["gpst_tow_s"] == 444954.0 and rec["since_start_s"] == 1.2
    assert all(abs(a - b) <= 5e-5 for a, b in zip(rec["x_ecef_m"], HKSC_ECEF_M, strict=True))
    assert abs(rec["lat_deg"] - fix.lat_deg) <= 1e-9 and abs(rec["lon_deg"] - fix.lon_deg) <= 1e-9
    assert abs(rec["alt_m"] - fix.alt_m) <= 1e-4
    assert rec["n_full"] == 5 and rec["n_frac"] == 3
    assert rec["ambiguity"] == {"C06": 69, "C09": 74, "C16": 71}
    assert list(rec["ambiguity"]) == ["C06", "C09", "C16"]
    assert rec["redundancy"] == 4 and rec["raim"] == "pass"
    assert rec["hpl_m"] == 14.25 and rec["vpl_m"] == 21.5 and rec["chi2_max"] == 28.473
    assert rec["std_enu_m"] == [0.338, 0.341, 0.792]
    assert validate(rec) == []
    line = fix_json_line(fix, since_start_s=1.2)
    assert "\n" not in line and " " not in line
    assert strict_loads(line) == rec


def test_spp_fix_omits_what_does_not_apply_and_since_start_when_not_given():
    rec = fix_record(hksc_fix("spp"))
    assert set(rec) == CONTRACT_FIX_FIELDS - {"reason", "gdop_full", "ambiguity", "since_start_s"}
    assert rec["n_frac"] == 0
    assert validate(rec) == []


def test_declined_fix_has_reason_and_no_position():
    rec = fix_record(declined_fix(), since_start_s=0.0)
    assert rec["mode"] == "none" and rec["reason"].startswith("GDOP gate failed")
    assert rec["gdop_full"] == 4812.3 and rec["since_start_s"] == 0.0
    for key in ("x_ecef_m", "lat_deg", "lon_deg", "alt_m", "clock_bias_m", "pdop"):
        assert key not in rec
    assert None not in rec.values()
    assert validate(rec) == []
    # a declined Fix must still say why, even when the solver forgot to
    rec = fix_record(declined_fix(decline=None, gdop_full=None))
    assert rec["reason"] and validate(rec) == []


def test_integrity_states_and_exclusions():
    untested = fix_record(hksc_fix(redundancy=0, chi2=None, chi2_max=None, hpl_m=None, vpl_m=None))
    assert untested["raim"] == "untested" and untested["redundancy"] == 0
    assert not {"chi2", "chi2_max", "hpl_m", "vpl_m"} & set(untested)
    unprotected = fix_record(hksc_fix(hpl_m=math.inf, vpl_m=math.inf))
    assert unprotected["raim"] == "unprotected" and "hpl_m" not in unprotected
    why = "chi-square test failed (812.5 > 28.5), w-test 27.9"
    excl = fix_record(hksc_fix(excluded={"C08": why}))
    assert excl["excluded"] == {"C08": why}
    declined = fix_record(declined_fix(excluded={"C08": why}))
    assert declined["reason_code"] == "gdop_gate" and declined["excluded"] == {"C08": why}
    for rec in (untested, unprotected, excl, declined):
        assert validate(rec) == []
    # a published fix without its integrity state, or a declined one with levels, is invalid
    assert validate({k: v for k, v in excl.items() if k != "raim"})
    assert validate(declined | {"hpl_m": 3.0})


def test_non_finite_values_are_omitted_and_numpy_scalars_serialise():
    fix = hksc_fix(
        resid_rms_m=float("nan"),
        pdop=float("inf"),
        gdop_full=np.float64(2.5),
        ambiguity={"C06": np.int64(69)},
    )
    rec = fix_record(fix, since_start_s=float("nan"))
    assert "resid_rms_m" not in rec and "pdop" not in rec and "since_start_s" not in rec
    assert type(rec["ambiguity"]["C06"]) is int and type(rec["gdop_full"]) is float
    assert strict_loads(fix_json_line(fix)) == fix_record(fix)
    broken = replace(hksc_fix(), x_ecef_m=(1.0, math.nan, 2.0))
    assert "x_ecef_m" not in fix_record(broken)
    strict_loads(fix_json_line(broken))


def test_csv_round_trips_through_the_csv_module():
    fixes = [
        hksc_fix(),
        hksc_fix("spp"),
        declined_fix(decline=Declined.of(Decline.NO_EPHEMERIS, prns='"C01", C02')),
    ]
    text = csv_header() + "\n" + "".join(fix_csv_row(f) + "\n" for f in fixes)
    rows = list(csv.DictReader(io.StringIO(text)))
    assert tuple(rows[0]) == CSV_COLUMNS
    fast, spp, none = rows
    assert [float(fast[c]) for c in ("x_ecef_m", "y_ecef_m", "z_ecef_m")] == pytest.approx(
        HKSC_ECEF_M, abs=1e-4
    )
    assert float(fast["lat_deg"]) == pytest.approx(fixes[0].lat_deg, abs=1e-9)
    assert fast["reason"] == "" and int(fast["n_frac"]) == 3
    assert spp["gdop_full"] == "" and spp["mode"] == "spp"
    assert none["x_ecef_m"] == none["lat_deg"] == none["pdop"] == ""
    assert none["reason"] == 'no usable ephemeris for "C01", C02'
    assert none["gdop_full"] == "4812.3"


def test_sky_track_status_records_validate():
    sky = sky_record(2161, 444954.0, SKY)
    assert validate(sky) == []
    assert [s["prn"] for s in sky["satellites"]] == [s.prn for s in SKY]
    c39 = sky["satellites"][-1]
    assert "cn0_dbhz" not in c39 and c39["used"] is False and c39["full"] is True
    wrap = sky_record(2161, 1.0, [SatView("C05", 30.0, 359.999, 40.0, False, False)])
    assert wrap["satellites"][0]["az_deg"] == 0.0 and validate(wrap) == []

    sow = track_record("C06", "sow", 2161, 444954.0, 3.0, "D1", sow_s=444936.0)
    full = track_record("C06", "full", 2161, 444954.1, 3.1, "D1", full_since_s=3.1)
    assert sow["sow_s"] == 444936.0 and "full_since_s" not in sow
    assert full["full_since_s"] == 3.1 and "sow_s" not in full
    assert validate(sow) == [] and validate(full) == []

    st = status_record({"frames_ubx": 10, "fixes": np.int64(3), "bad": float("nan")}, uptime_s=2.5)
    assert st == {
        "class": "STATUS",
        "uptime_s": 2.5,
        "counters": {"fixes": 3, "frames_ubx": 10},
    }
    assert validate(st) == []
    strict_loads(json.dumps(st, allow_nan=False))


def test_schema_fields_are_the_contract():
    assert set(SCHEMAS) == {"FIX", "SKY", "TRACK", "STATUS"}
    assert (
        set(SCHEMAS["FIX"]["properties"])
        == CONTRACT_FIX_FIELDS | CONDITIONAL_FIX_FIELDS | VELOCITY_FIX_FIELDS
    )
    for cls, schema in SCHEMAS.items():
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        Draft202012Validator.check_schema(schema)  # a valid schema by the metaschema
        assert schema["properties"]["class"] == {"const": cls}
        json.dumps(schema)  # plain JSON data, publishable as a .json file


GOOD_FIX = {
    "class": "FIX",
    "solver": "fast",
    "mode": "fast",
    "gpst_week": 2161,
    "gpst_tow_s": 444954.0,
    "x_ecef_m": [-2414266.9197, 5386768.9868, 2407460.0314],
    "lat_deg": 22.32,
    "lon_deg": 114.14,
    "alt_m": 20.0,
    "clock_bias_m": 1.0,
    "n_full": 5,
    "n_frac": 3,
    "ambiguity": {"C06": 69},
    "raim": "untested",
}
GOOD_NONE = {
    "class": "FIX",
    "solver": "spp",
    "mode": "none",
    "gpst_week": 2161,
    "gpst_tow_s": 1.0,
    "n_full": 3,
    "n_frac": 0,
    "reason": "too few full measurements",
}
GOOD_TRACK = {
    "class": "TRACK",
    "prn": "C06",
    "event": "sow",
    "nav_type": "D1",
    "gpst_week": 2161,
    "gpst_tow_s": 1.0,
    "since_start_s": 0.5,
    "sow_s": 444936.0,
}
GOOD_SKY = {
    "class": "SKY",
    "gpst_week": 2161,
    "gpst_tow_s": 1.0,
    "satellites": [{"prn": "C01", "el_deg": 47.3, "az_deg": 123.4, "used": True, "full": True}],
}

# (record, where jsonschema must report it, the schema keyword that fails, a fragment of its
# message or "")
BAD = [
    ({k: v for k, v in GOOD_FIX.items() if k != "n_full"}, "$", "required", "'n_full'"),
    ({**GOOD_FIX, "pdop": None}, "$.pdop", "type", "'number'"),
    ({**GOOD_FIX, "speed_mps": 1.0}, "$", "additionalProperties", "'speed_mps'"),
    ({**GOOD_FIX, "gpst_week": "2161"}, "$.gpst_week", "type", "'integer'"),
    ({**GOOD_FIX, "gpst_week": 2161.5}, "$.gpst_week", "type", "'integer'"),
    ({**GOOD_FIX, "n_frac": True}, "$.n_frac", "type", "'integer'"),
    ({**GOOD_FIX, "n_frac": -1}, "$.n_frac", "minimum", ""),
    ({**GOOD_FIX, "mode": "rtk"}, "$.mode", "enum", "'rtk'"),
    ({**GOOD_FIX, "solver": "none"}, "$.solver", "enum", "'none'"),
    ({**GOOD_FIX, "lat_deg": 91.0}, "$.lat_deg", "maximum", ""),
    ({**GOOD_FIX, "gpst_tow_s": 604800.0}, "$.gpst_tow_s", "exclusiveMaximum", ""),
    ({**GOOD_FIX, "alt_m": float("nan")}, "$.alt_m", "type", "'number'"),
    ({**GOOD_FIX, "x_ecef_m": [1.0, 2.0]}, "$.x_ecef_m", "minItems", ""),
    ({**GOOD_FIX, "x_ecef_m": [1.0, 2.0, "3"]}, "$.x_ecef_m[2]", "type", "'number'"),
    ({**GOOD_FIX, "ambiguity": {"R05": 1}}, "$.ambiguity", "additionalProperties", "'R05'"),
    ({**GOOD_FIX, "ambiguity": {"C05": 1.5}}, "$.ambiguity.C05", "type", "'integer'"),
    ({**GOOD_FIX, "ambiguity": {}}, "$.ambiguity", "minProperties", ""),
    ({**GOOD_FIX, "reason": "x"}, "$", "not", ""),  # a fix with a position has no reason
    ({**GOOD_FIX, "clocks_m": {"C": 1.0}}, "$.clocks_m", "minProperties", ""),
    ({**GOOD_FIX, "clocks_m": {"C": 1.0, "GPS": 2.0}}, "$.clocks_m", "additionalProperties", ""),
    ({**GOOD_NONE, "clocks_m": {"C": 1.0, "G": 2.0}}, "$", "not", ""),
    ({k: v for k, v in GOOD_FIX.items() if k != "lat_deg"}, "$", "required", "'lat_deg'"),
    ({**GOOD_NONE, "lat_deg": 22.0}, "$", "not", ""),  # a declined fix has no position
    ({k: v for k, v in GOOD_NONE.items() if k != "reason"}, "$", "required", "'reason'"),
    ({**GOOD_NONE, "reason": ""}, "$.reason", "minLength", ""),
    ({**GOOD_TRACK, "event": "lost"}, "$.event", "enum", "'lost'"),
    ({k: v for k, v in GOOD_TRACK.items() if k != "sow_s"}, "$", "required", "'sow_s'"),
    ({**GOOD_TRACK, "prn": "C6"}, "$.prn", "pattern", ""),
    ({**GOOD_TRACK, "nav_type": "D3"}, "$.nav_type", "enum", "'D3'"),
    (
        {**GOOD_SKY, "satellites": [{"prn": "C01", "used": 1, "full": True}]},
        "$.satellites[0].used",
        "type",
        "'boolean'",
    ),
    (
        {**GOOD_SKY, "satellites": [{"prn": "C01", "az_deg": 360.0, "used": True, "full": True}]},
        "$.satellites[0].az_deg",
        "exclusiveMaximum",
        "",
    ),
    ({"class": "STATUS", "counters": {"frames": "7"}}, "$.counters.frames", "type", "'number'"),
    ({"class": "STATUS", "counters": {}, "extra": [1]}, "$.extra", "type", ""),
    ({"class": "STATUS"}, "$", "required", "'counters'"),
    ({"class": "TPV"}, "$.class", "enum", "'TPV'"),
    ([GOOD_FIX], "$", "type", "'object'"),
]


@pytest.mark.parametrize("good", [GOOD_FIX, GOOD_NONE, GOOD_TRACK, GOOD_SKY])
def test_schemas_accept_hand_written_good_records(good):
    assert validate(good) == []
    # JSON Schema: 1.0 is an integer (draft 2020-12, section 6.1.1)
    assert validate({**good, "gpst_week": 2161.0}) == []


@pytest.mark.parametrize(
    ("record", "path", "keyword", "fragment"),
    BAD,
    ids=[f"{path} {keyword} {fragment}".strip() for _, path, keyword, fragment in BAD],
)
def test_schemas_reject_hand_written_bad_records(record, path, keyword, fragment):
    errors = schema_errors(record)
    assert errors, record
    assert any(
        e.json_path == path and e.validator == keyword and fragment in e.message for e in errors
    ), [(e.json_path, e.validator, e.message) for e in errors]


def test_every_golden_replay_record_validates():
    """Every record a replay wrote (FIX, TRACK) and every run's final STATUS; the GOLDEN
    header naming the case is the test's own, not a published record."""
    files = sorted(GOLDEN.glob("*.jsonl"))
    assert files
    n = 0
    classes = set()
    for path in files:
        for line in path.read_text().splitlines():
            rec = strict_loads(line)
            if rec["class"] == "GOLDEN":
                continue
            assert validate(rec) == [], (path.name, rec, validate(rec))
            classes.add(rec["class"])
            n += 1
    assert n > 1000 and classes == {"FIX", "TRACK", "STATUS"}


def test_velocity_fields_come_together_and_validate():
    vel = Velocity(
        v_enu_m_s=(3.0, -4.0, 0.12345),
        std_v_enu_m_s=(0.02, 0.03, 0.05),
        speed_m_s=5.0,
        std_speed_m_s=0.0264,
        course_deg=359.999,
        std_course_deg=0.3,
        clock_drift_m_s=-123.45678,
        std_clock_drift_m_s=0.04,
    )
    rec = fix_record(replace(hksc_fix(), velocity=vel))
    assert set(rec) >= VELOCITY_FIX_FIELDS and validate(rec) == []
    assert rec["v_enu_m_s"] == [3.0, -4.0, 0.1235] and rec["speed_m_s"] == 5.0
    assert rec["course_deg"] == 0.0  # 359.999 to 0.01 deg is 360, which is 0
    assert rec["clock_drift_m_s"] == -123.4568
    row = dict(
        zip(
            csv_header().split(","),
            next(csv.reader([fix_csv_row(replace(hksc_fix(), velocity=vel))])),
            strict=True,
        )
    )
    assert (row["v_east_m_s"], row["v_north_m_s"], row["speed_m_s"]) == ("3.0", "-4.0", "5.0")
    # a velocity with a non-finite value gives none of the fields
    bad = replace(vel, std_course_deg=math.nan)
    assert not VELOCITY_FIX_FIELDS & set(fix_record(replace(hksc_fix(), velocity=bad)))
    # the schema refuses a record with only some of them, and any on a declined fix
    partial = {k: v for k, v in rec.items() if k != "std_speed_m_s"}
    assert validate(partial)
    declined = fix_record(declined_fix())
    assert validate(declined | {k: rec[k] for k in VELOCITY_FIX_FIELDS})
