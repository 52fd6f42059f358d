"""The plain NMEA formatter (:func:`service.output.nmea.plain_sentence`) against pynmeagps.

pynmeagps' ``NMEAMessage`` is the independent reference: every sentence the service builds
must be byte-identical to the one pynmeagps builds from the same fields, and must parse back
with pynmeagps' ``NMEAReader`` (checksum validated). Checked for every sentence of every
golden capture's replay, for generated fixes and for generated field values.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pynmeagps import VALCKSUM, NMEAReader

import service.output.nmea as nmea
from service.commands.cli import main
from service.core.types import SatView, Velocity
from tests.support.fixes import declined_fix, ecef_m, hksc_fix
from tests.system.test_replay_golden import CASES, NO_RECORDS, _args

Serializer = Callable[[str, str, dict[str, object]], bytes]


@contextmanager
def serializer(fn: Serializer) -> Iterator[None]:
    saved = nmea._serialize
    nmea._serialize = fn
    try:
        yield
    finally:
        nmea._serialize = saved


def parses_back(sentence: bytes) -> None:
    msg = NMEAReader.parse(sentence, validate=VALCKSUM)
    assert msg is not None
    assert sentence.startswith(f"${msg.talker}{msg.msgID},".encode())


class Compared:
    """A serializer that writes with the plain formatter and checks each sentence against
    pynmeagps, counting sentences per type."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.mismatches: list[tuple[bytes, bytes]] = []

    def __call__(self, talker: str, msg_id: str, fields: dict[str, object]) -> bytes:
        got = nmea.plain_sentence(talker, msg_id, fields)
        want = nmea.pynmeagps_sentence(talker, msg_id, fields)
        if got != want:
            self.mismatches.append((got, want))
        self.counts[msg_id] = self.counts.get(msg_id, 0) + 1
        return got


GOLDEN_WITH_FIXES = [n for n, c in CASES.items() if c.fixes not in NO_RECORDS]


@pytest.mark.parametrize("name", GOLDEN_WITH_FIXES)
def test_every_sentence_of_a_golden_replay_is_what_pynmeagps_builds(name, tmp_path: Path):
    out = tmp_path / "out.nmea"
    compared = Compared()
    with serializer(compared):
        rc = main(["replay", *_args(CASES[name].args), "--max-speed", "--nmea-out", str(out)])
    assert rc == 0
    assert not compared.mismatches[:3]
    written = out.read_bytes().splitlines(keepends=True)
    assert compared.counts.get("GGA", 0) >= 1 and sum(compared.counts.values()) == len(written)
    for sentence in written:
        parses_back(sentence)


def test_golden_replays_cover_every_sentence_type(tmp_path: Path):
    compared = Compared()
    with serializer(compared):
        for name in ("polyu-f9p-ubx", "hksc-rinex"):
            out = tmp_path / f"{name}.nmea"
            main(["replay", *_args(CASES[name].args), "--max-speed", "--nmea-out", str(out)])
    assert set(compared.counts) == {"GGA", "RMC", "VTG", "GSA", "GSV", "GST", "ZDA"}
    assert not compared.mismatches


finite = st.floats(allow_nan=False, allow_infinity=False)
sky_sat = st.builds(
    SatView,
    st.one_of(  # (a GSV per talker: BeiDou's, GPS's and Galileo's satellites)
        st.integers(1, 63).map(lambda n: f"C{n:02d}"),
        st.integers(1, 32).map(lambda n: f"G{n:02d}"),
        st.integers(1, 36).map(lambda n: f"E{n:02d}"),
    ),
    st.one_of(st.floats(-90, 90), st.just(math.nan)),
    st.one_of(st.floats(-360, 720), st.just(math.nan)),
    st.one_of(st.floats(0, 60), st.just(math.nan)),
    st.booleans(),
    st.booleans(),
)
maybe_dop = st.one_of(st.none(), st.floats(0, 1e4), st.just(math.inf), st.just(math.nan))
sigma = st.one_of(st.floats(0, 1e6), st.just(math.inf))
speed = st.one_of(st.floats(0, 1e4), st.sampled_from([0.0, 0.0005, 1e-9]))
velocity = st.builds(
    Velocity,
    st.tuples(finite, finite, finite),
    st.tuples(sigma, sigma, sigma),
    speed,
    sigma,
    st.one_of(st.floats(0, 360, exclude_max=True), st.sampled_from([359.999, 0.004])),
    st.one_of(st.floats(0, 180), st.sampled_from([10.0, 10.0001])),
    finite,
    sigma,
)


@st.composite
def fixes(draw: st.DrawFn):
    lat = draw(
        st.one_of(st.floats(-90, 90), st.sampled_from([22.99999999999, -0.0, 59.999999999999]))
    )
    lon = draw(st.one_of(st.floats(-180, 180), st.sampled_from([-113.99999999999, 179.9999999])))
    alt = draw(st.floats(-500, 99_999))
    used = draw(st.lists(st.integers(1, 63), unique=True, max_size=16))
    cov = draw(
        st.one_of(
            st.none(),
            st.tuples(st.floats(0, 1e4), st.floats(-1e3, 1e3), st.floats(0, 1e4)).map(
                lambda v: ((v[0], v[1], 0.0), (v[1], v[2], 0.0), (0.0, 0.0, 1.0))
            ),
        )
    )
    fix = hksc_fix(
        x_ecef_m=ecef_m(lat, lon, alt),
        lat_deg=lat,
        lon_deg=lon,
        alt_m=alt,
        hdop=draw(maybe_dop),
        pdop=draw(maybe_dop),
        vdop=draw(maybe_dop),
        used=tuple(f"C{n:02d}" for n in used),
        std_enu_m=draw(st.one_of(st.none(), st.tuples(sigma, sigma, sigma))),
        cov_enu_m2=cov,
        resid_rms_m=draw(st.one_of(st.none(), st.floats(0, 1e5))),
        sky=tuple(draw(st.lists(sky_sat, max_size=45))),
        clock_bias_m=draw(st.floats(-3e5, 3e5)),
        velocity=draw(st.one_of(st.none(), velocity)),
    )
    if draw(st.booleans()):
        return declined_fix(gpst_tow_s=fix.gpst_tow_s, used=fix.used[:3])
    return fix


utcs = st.one_of(
    st.none(),
    st.datetimes(dt.datetime(1999, 12, 31), dt.datetime(2099, 12, 31)).map(nmea.nmea_time),
)


@given(
    fix=fixes(),
    utc=utcs,
    talker=st.sampled_from(nmea.TALKERS),
    gsa_talker=st.one_of(st.none(), st.sampled_from(nmea.TALKERS)),
    time_known=st.booleans(),
)
def test_generated_fixes_give_the_sentences_pynmeagps_builds(
    fix, utc, talker, gsa_talker, time_known
):
    if utc is None and fix.ok:
        fix = replace(fix, mode="none")
    kwargs = {"utc": utc, "talker": talker, "gsa_talker": gsa_talker, "time_known": time_known}
    got = nmea.sentences_for_fix(fix, **kwargs)
    with serializer(nmea.pynmeagps_sentence):
        want = nmea.sentences_for_fix(fix, **kwargs)
    assert got == want
    for sentence in got:
        parses_back(sentence)


field_value = st.one_of(
    finite,
    st.integers(-(10**6), 10**6),
    st.just(""),
    st.text("ABCNSEWV0123456789.-", max_size=6),
)


@given(
    msg_id=st.sampled_from(["GGA", "RMC", "VTG", "GSA", "GSV", "GST", "ZDA"]),
    values=st.dictionaries(
        st.sampled_from(
            [
                "lat",
                "lon",
                "quality",
                "numSV",
                "HDOP",
                "alt",
                "altUnit",
                "sep",
                "diffAge",
                "status",
                "spd",
                "cog",
                "mv",
                "mvEW",
                "posMode",
                "navStatus",
                "opMode",
                "navMode",
                "PDOP",
                "VDOP",
                "systemId",
                "numMsg",
                "msgNum",
                "rangeRms",
                "stdMajor",
                "orient",
                "stdAlt",
                "day",
                "month",
                "year",
                "ltzh",
                "signalID",
                *(f"svid_{j:02d}" for j in range(1, 13)),
                "elv_01",
                "az_02",
                "cno_03",
                "cogt",
                "cogtUnit",
                "cogm",
                "sogn",
                "sogk",
                "sogkUnit",
            ]
        ),
        field_value,
    ),
    when=st.datetimes(dt.datetime(2000, 1, 1), dt.datetime(2099, 12, 31)).map(nmea.nmea_time),
)
def test_any_fields_give_the_bytes_pynmeagps_writes(msg_id, values, when):
    fields: dict[str, object] = {"time": when.time(), "date": when.date(), **values}
    if msg_id in ("GSA", "GSV") and "svid_01" not in fields:
        fields["svid_01"] = 7
    assert nmea.plain_sentence("GN", msg_id, fields) == nmea.pynmeagps_sentence(
        "GN", msg_id, fields
    )


leap_utcs = st.sampled_from(
    [dt.datetime(2016, 12, 31, 23, 59, 59, 990_000), dt.datetime(2017, 1, 1, 0, 0, 0)]
)


@settings(max_examples=300, deadline=None)
@given(fix=fixes(), utc=st.one_of(utcs, leap_utcs), talker=st.sampled_from(nmea.TALKERS))
def test_lead_sentences_written_directly_are_the_plain_formatters(fix, utc, talker):
    """RMC, VTG and GGA, which ``lead_sentences`` writes without field dicts on the path to
    GGA, are the bytes the plain formatter writes from its field dicts (the generic path,
    taken whenever another serializer is set), for fixes, declines and times of all kinds."""
    if utc is None and fix.ok:
        fix = replace(fix, mode="none")
    got = nmea.lead_sentences(fix, utc=utc, talker=talker)
    with serializer(lambda t, m, f: nmea.plain_sentence(t, m, f)):
        want = nmea.lead_sentences(fix, utc=utc, talker=talker)
    assert got == want
