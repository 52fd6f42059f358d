"""Fuzzing (hypothesis) of every driver's byte parser: what may escape, and no hangs.

The driver boundary and what may cross it:

- :class:`drivers.source.StreamDecoder` ``feed``/``flush`` (framer, UBX, RTCM3, SBF, NMEA and
  gpsd-comment skipping): nothing, ever.
- :class:`drivers.framing.Framer`: nothing; every frame it returns is checksum-valid by the
  libraries' own helpers (pyubx2 Fletcher, pyrtcm CRC-24Q, pysbf2 CRC-16). SBF blocks are
  fuzzed in ``tests/drivers/test_sbf.py``.
- The mappers (:class:`drivers.ubx.UbxMapper`, :class:`drivers.rtcm.RtcmMapper`) given a
  message the library *did* parse: at most :class:`~service.core.errors.DecodeError`.
- RINEX (:class:`drivers.rinex.RinexObsReader`, :func:`drivers.rinex.read_nav`): at most
  :class:`~service.core.errors.FramingError`; in lenient mode the observation data section
  raises nothing.
- B1I subframes (:func:`drivers.sfrbx.nav_subframe_from_sfrbx`,
  :func:`service.core.bds_nav.parse_header`, :class:`service.core.bds_nav.EphemerisAssembler`):
  None / DecodeError / nothing respectively.

Inputs are random bytes and mutations of real frames from the captures, re-sealed with the
libraries' checksum helpers so that the mutated content reaches the mappers. Each call runs
under a generous wall-clock alarm that only detects hangs (no performance is asserted).
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import signal
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyrtcm import RTCMReader
from pyrtcm.rtcmhelpers import calc_crc24q
from pysbf2.sbfhelpers import calc_crc as calc_sbf_crc
from pyubx2 import UBXReader
from pyubx2.ubxhelpers import calc_checksum

from drivers.framing import Framer, WeekContext
from drivers.protocols import PROTOCOLS
from drivers.rinex import RinexObsReader, read_nav
from drivers.rtcm import RtcmMapper
from drivers.sfrbx import nav_subframe_from_sfrbx
from drivers.source import StreamDecoder
from drivers.ubx import UbxMapper
from service.core.bds_nav import EphemerisAssembler, parse_header
from service.core.errors import DecodeError, FramingError
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    ReceiverFix,
    TimeOffset,
)
from tests.support.paths import DATA

HANG_S = 20.0
"""Per-call wall bound: a hang detector only, far above any normal call."""
FUZZ = settings(
    max_examples=int(os.environ.get("BDSFIX_FUZZ_EXAMPLES", "120")),  # more for a long hunt
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
EVENT_TYPES = (
    MeasurementEpoch,
    NavSubframe,
    Ephemeris,
    KlobucharParams,
    ReceiverFix,
    TimeOffset,
)
CAPTURES = (
    "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx",
    "ublox-logs/ublox-zed-f9r.log",
    "ublox-logs/ublox-zed-f9p-sfrbx.log",
    "tiny-ubx-rtcm/pygpsdata-RTCM3.log",
)


class Hang(Exception):
    """A call outlived :data:`HANG_S`."""


@contextlib.contextmanager
def hang_guard(seconds: float = HANG_S) -> Iterator[None]:
    def fire(*_: Any) -> None:
        raise Hang(f"call did not return within {seconds} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@functools.cache
def library_frames() -> dict[str, tuple[bytes, ...]]:
    """Real frames by kind, split by pyubx2's own stream reader (not by the code under test)."""
    kinds: dict[str, list[bytes]] = {}
    for name in CAPTURES:
        with open(DATA / name, "rb") as s:
            for raw, msg in UBXReader(s, protfilter=7, quitonerror=0):
                if raw is None:
                    continue
                if raw[:1] == b"\xb5":
                    key = str(msg.identity) if msg is not None else "ubx?"
                elif raw[:1] == b"\xd3":
                    key = f"rtcm{((raw[3] << 4) | (raw[4] >> 4))}"
                else:
                    key = "nmea"
                kinds.setdefault(key, []).append(bytes(raw))
    # a few of each kind keep the strategies small
    return {k: tuple(v[:: max(1, len(v) // 12)][:12]) for k, v in kinds.items()}


def frames_of(*keys: str) -> tuple[bytes, ...]:
    lib = library_frames()
    return tuple(f for k in keys for f in lib.get(k, ()))


UBX_USED = ("RXM-RAWX", "RXM-MEASX", "RXM-SFRBX", "NAV-TIMEGPS", "NAV-PVT")
RTCM_USED = ("rtcm1042", "rtcm1124", "rtcm1125", "rtcm1126", "rtcm1127", "rtcm1077")


def reseal_ubx(body: bytes) -> bytes:
    """UBX frame from class, id and payload (length recomputed), Fletcher by pyubx2."""
    head = body[:2].ljust(2, b"\x00")
    payload = body[2:]
    inner = head + len(payload).to_bytes(2, "little") + payload
    return b"\xb5\x62" + inner + calc_checksum(inner)


def reseal_rtcm(payload: bytes) -> bytes:
    payload = payload[:1023] or b"\x00"
    head = b"\xd3" + len(payload).to_bytes(2, "big")
    return head + payload + calc_crc24q(head + payload).to_bytes(3, "big")


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` with a few byte flips, inserts, deletes or truncations."""
    buf = bytearray(data)
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "cut"]))
        if not buf and op != "insert":
            continue
        i = draw(st.integers(0, max(0, len(buf) - 1)))
        if op == "flip":
            buf[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            buf[i] = draw(st.sampled_from([0x00, 0xFF, 0x7F, 0x80, 0x01, 0xFE]))
        elif op == "insert":
            buf[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del buf[i : i + draw(st.integers(1, 8))]
        else:
            del buf[i:]
    return bytes(buf)


def mutated_payload_frames(keys: tuple[str, ...], reseal: Any, skip: int) -> st.SearchStrategy:
    """Real frames whose content is mutated, then re-sealed so the checksum holds."""
    return st.sampled_from(frames_of(*keys)).flatmap(
        lambda raw: mutated(raw[skip:-2] if skip == 2 else raw[3:-3]).map(reseal)
    )


ubx_content = mutated_payload_frames(UBX_USED, reseal_ubx, 2)
rtcm_content = mutated_payload_frames(RTCM_USED, reseal_rtcm, 3)
real_any = st.sampled_from([f for v in library_frames().values() for f in v])
stream_part = st.one_of(
    st.binary(max_size=200),
    real_any,
    real_any.flatmap(mutated),
    ubx_content,
    rtcm_content,
    st.sampled_from([b"\xb5\x62\x02\x15\xff\xff", b"\xd3\x03\xff", b"$GNGGA,", b"\n#", b"\r\n"]),
)
streams = st.lists(stream_part, max_size=10).map(b"".join)


def feed_in_chunks(target: Any, data: bytes, cuts: list[int]) -> list[Any]:
    out: list[Any] = []
    prev = 0
    for cut in [*sorted({min(c, len(data)) for c in cuts}), len(data)]:
        with hang_guard():
            out += target.feed(data[prev:cut])
        prev = cut
    with hang_guard():
        out += target.flush()
    return out


# --- framer and stream decoder: nothing escapes --------------------------------------------


@FUZZ
@given(streams, st.lists(st.integers(0, 20000), max_size=8))
def test_framer_never_raises_and_frames_pass_library_checksums(data, cuts):
    framer = Framer(PROTOCOLS, max_payload={"ubx": 65535})
    for frame in feed_in_chunks(framer, data, cuts):
        raw = frame.raw
        if frame.protocol == "ubx":
            assert calc_checksum(raw[2:-2]) == raw[-2:]
        elif frame.protocol == "rtcm":
            assert calc_crc24q(raw[:-3]) == int.from_bytes(raw[-3:], "big")
        elif frame.protocol == "sbf":
            assert calc_sbf_crc(raw[4:]) == int.from_bytes(raw[2:4], "little")
        else:
            assert raw.startswith(b"$") and raw.endswith(b"\n")
    assert framer.buffered == 0


@FUZZ
@given(streams, st.lists(st.integers(0, 20000), max_size=8), st.none() | st.integers(0, 4000))
def test_stream_decoder_feed_and_flush_never_raise(data, cuts, week):
    dec = StreamDecoder(gps_week=week)
    events = feed_in_chunks(dec, data, cuts)
    assert all(isinstance(e, EVENT_TYPES) for e in events)
    for e in events:
        if isinstance(e, MeasurementEpoch):  # a full pseudorange is a range or NaN
            pr = np.asarray(e.pr_m, dtype=float)
            assert np.all(np.isnan(pr) | ((pr > 0) & (pr < 1e8)))
            assert np.all(np.isfinite(e.frac_pr_m))
    with hang_guard():
        assert dec.flush() == []  # a second flush has nothing left


@FUZZ
@given(st.binary(max_size=3000), st.lists(st.integers(0, 3000), max_size=8))
def test_stream_decoder_random_bytes(data, cuts):
    dec = StreamDecoder()
    events = feed_in_chunks(dec, data, cuts)
    assert all(isinstance(e, EVENT_TYPES) for e in events)


# --- mappers: a message the library parsed maps or raises DecodeError ----------------------


def library_parse(reader: Any, raw: bytes) -> Any:
    """The library's parse of a frame, or None when the library itself refuses it."""
    try:
        return reader.parse(raw)
    except Exception:
        return None


def _map_library_parsed(mapper, reader, frames) -> None:
    """Feed the messages the library parses to a mapper: only events or DecodeError, no hang."""
    for raw in frames:
        msg = library_parse(reader, raw)
        if msg is None:  # the library refused it: StreamDecoder counts that case
            continue
        with hang_guard(), contextlib.suppress(DecodeError):
            events = mapper.on_message(msg)
            assert all(isinstance(e, EVENT_TYPES) for e in events)
    with hang_guard():
        mapper.flush()


@FUZZ
@given(st.lists(ubx_content, min_size=1, max_size=6))
def test_ubx_mapper_on_library_parsed_messages(frames):
    _map_library_parsed(UbxMapper(week=WeekContext(2300)), UBXReader, frames)


@FUZZ
@given(st.lists(rtcm_content, min_size=1, max_size=6), st.none() | st.integers(0, 4000))
def test_rtcm_mapper_on_library_parsed_messages(frames, week):
    _map_library_parsed(RtcmMapper(week=WeekContext(week)), RTCMReader, frames)


# --- B1I subframes ----------------------------------------------------------------------------

words30 = st.integers(0, (1 << 30) - 1)
any_words = st.lists(st.integers(-(1 << 33), 1 << 33) | words30, min_size=0, max_size=12)


@functools.cache
def real_subframes() -> tuple[tuple[int, tuple[int, ...]], ...]:
    out = []
    for raw in frames_of("RXM-SFRBX"):
        msg = UBXReader.parse(raw)
        if int(msg.gnssId) == 3 and int(msg.numWords) == 10:
            out.append((int(msg.svId), tuple(getattr(msg, f"dwrd_{i:02d}") for i in range(1, 11))))
    return tuple(out)


@st.composite
def damaged_subframe(draw: st.DrawFn) -> tuple[int, list[int]]:
    sv, words = draw(st.sampled_from(real_subframes()))
    out = [w & ((1 << 30) - 1) for w in words]
    for _ in range(draw(st.integers(0, 5))):
        k = draw(st.integers(0, 9))
        out[k] ^= 1 << draw(st.integers(0, 29))
    return sv, out


@FUZZ
@given(st.one_of(any_words, damaged_subframe().map(lambda t: t[1])), st.sampled_from(["D1", "D2"]))
def test_parse_header_raises_only_decode_error(words, nav_type):
    with hang_guard(), contextlib.suppress(DecodeError):
        head = parse_header(words, nav_type)
        assert 1 <= head.fra_id <= 5 and 0 <= head.sow_s < 604800


@FUZZ
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["C01", "C06", "C14"]),
            st.sampled_from(["D1", "D2", "D3"]),
            st.one_of(any_words, damaged_subframe().map(lambda t: t[1])),
        ),
        max_size=20,
    )
)
def test_ephemeris_assembler_never_raises(items):
    asm = EphemerisAssembler()
    for prn, nav_type, words in items:
        with hang_guard():
            out = asm.feed(prn, nav_type, words)
        assert all(isinstance(e, Ephemeris | KlobucharParams) for e in out)


@FUZZ
@given(damaged_subframe(), st.integers(0, 255), st.integers(0, 15), st.integers(0, 40))
def test_sfrbx_mapper_returns_subframe_or_none(sub, gnss_id, sig_id, num_words):
    sv, words = sub
    # UBX-RXM-SFRBX: gnssId, svId, sigId, freqId, numWords, chn, version, reserved, dwrd[n]
    body = [(words[k] if k < len(words) else 0) for k in range(num_words)]
    payload = bytes([gnss_id, sv, sig_id, 0, num_words, 0, 2, 0])
    payload += b"".join(w.to_bytes(4, "little") for w in body)
    try:
        msg = UBXReader.parse(reseal_ubx(b"\x02\x13" + payload))
    except Exception:
        return
    with hang_guard():
        got = nav_subframe_from_sfrbx(msg, 2300, 100.0)
    assert got is None or isinstance(got, NavSubframe)


# --- RINEX -----------------------------------------------------------------------------------

OBS = DATA / "hksc-2021/hksc1610.obs"
NAV = DATA / "hksc-2021/hksc1610.nav"


@functools.cache
def rinex_lines(path: Path, n_data: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(header lines, the first ``n_data`` data lines) of a real RINEX file."""
    lines = path.read_text().splitlines(keepends=True)
    end = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    return tuple(lines[:end]), tuple(lines[end : end + n_data])


printable_line = st.text(
    alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=90
).map(lambda s: s + "\n")


@st.composite
def mutated_lines(draw: st.DrawFn, lines: tuple[str, ...]) -> list[str]:
    out = list(lines)
    for _ in range(draw(st.integers(0, 6))):
        if not out:
            break
        i = draw(st.integers(0, len(out) - 1))
        op = draw(st.sampled_from(["char", "digits", "delete", "dup", "insert", "inf", "cut"]))
        line = out[i]
        if op == "char" and len(line) > 1:
            j = draw(st.integers(0, len(line) - 2))
            c = draw(st.sampled_from(list("x 9-.>C*+eDn\t\x00")))
            out[i] = line[:j] + c + line[j + 1 :]
        elif op == "digits" and len(line) > 1:
            j = draw(st.integers(0, len(line) - 2))
            k = min(len(line) - 1, j + draw(st.integers(1, 12)))
            out[i] = line[:j] + draw(st.sampled_from(["9" * (k - j), "0" * (k - j)])) + line[k:]
        elif op == "inf":
            out[i] = line.replace("D", "D3", 1).replace("E+", "E+4", 1)
            out[i] = out[i].replace("0.", "inf", 1) if draw(st.booleans()) else out[i]
        elif op == "delete":
            del out[i]
        elif op == "dup":
            out.insert(i, line)
        elif op == "insert":
            out.insert(i, draw(printable_line))
        else:
            out[i] = line[: draw(st.integers(0, len(line)))]
    return out


def write_tmp(lines: list[str], suffix: str) -> Path:
    fd, name = tempfile.mkstemp(suffix=suffix)
    with open(fd, "w", encoding="ascii", errors="replace") as f:
        f.write("".join(lines))
    return Path(name)


@FUZZ
@given(st.data())
def test_rinex_obs_raises_only_framing_error(data):
    head, body = rinex_lines(OBS, 400)
    mutate_header = data.draw(st.booleans())
    lines = (
        data.draw(mutated_lines(head)) + list(body)
        if mutate_header
        else list(head) + data.draw(mutated_lines(body))
    )
    path = write_tmp(lines, ".obs")
    try:
        for lenient in (False, True):
            try:
                with hang_guard():
                    reader = RinexObsReader(path, lenient=lenient)
            except FramingError:
                continue
            with hang_guard():
                if lenient:  # a lenient reader skips and counts, it never raises
                    epochs = list(reader)
                    assert all(isinstance(e, MeasurementEpoch) for e in epochs)
                else:
                    with contextlib.suppress(FramingError):
                        for e in reader:
                            assert isinstance(e, MeasurementEpoch)
    finally:
        path.unlink()


@FUZZ
@given(st.data())
def test_rinex_nav_raises_only_framing_error(data):
    head, body = rinex_lines(NAV, 240)
    lines = (
        data.draw(mutated_lines(head)) + list(body)
        if data.draw(st.booleans())
        else list(head) + data.draw(mutated_lines(body))
    )
    path = write_tmp(lines, ".nav")
    try:
        with hang_guard(), contextlib.suppress(FramingError):
            nav = read_nav(path)
            assert all(isinstance(e, Ephemeris) for v in nav.ephemerides.values() for e in v)
    finally:
        path.unlink()


@pytest.mark.parametrize(
    "text",
    [
        "",
        "\x00" * 100,
        "RINEX VERSION / TYPE\n" * 3,
        "     3.04           OBSERVATION DATA    M                   RINEX VERSION / TYPE\n",
    ],
)
def test_rinex_degenerate_files(tmp_path, text):
    p = tmp_path / "x.obs"
    p.write_text(text)
    with pytest.raises(FramingError):
        list(RinexObsReader(p, lenient=True))
    with pytest.raises(FramingError):
        read_nav(p)


# --- the bugs the fuzzers found, as fixed cases ------------------------------------------------


def _nav_with(tmp_path: Path, line_offset: int, old: str, new: str) -> Path:
    lines = NAV.read_text().splitlines(keepends=True)
    first = next(i for i, line in enumerate(lines) if line.startswith("C01"))
    assert old in lines[first + line_offset]
    lines[first + line_offset] = lines[first + line_offset].replace(old, new, 1)
    out = tmp_path / NAV.name
    out.write_text("".join(lines))
    return out


def test_nav_integer_field_beyond_double_range_is_a_framing_error(tmp_path):
    # BROADCAST ORBIT - 6 SatH1 (health) with an exponent past 1e308 (OverflowError before)
    bad = _nav_with(tmp_path, 6, "  .000000000000D+00 -.55", " .100000000000D+999 -.55")
    with pytest.raises(FramingError, match=rf"{NAV.name}:\d+: BDS record for C01: health"):
        read_nav(bad)


def test_glonass_time_epoch_near_year_one_is_a_framing_error(tmp_path):
    lines = OBS.read_text().splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if "TIME OF FIRST OBS" in line)
    lines[k] = lines[k][:48] + "GLO" + lines[k][51:]
    e = next(i for i, line in enumerate(lines) if line.startswith(">"))
    lines[e] = ">    1 01 01 00 00" + lines[e][18:]  # UTC(SU) - 3 h falls before year 1
    bad = tmp_path / OBS.name
    bad.write_text("".join(lines))
    with pytest.raises(FramingError, match=rf"{OBS.name}:{e + 1}: bad epoch line"):
        list(RinexObsReader(bad))
    reader = RinexObsReader(bad, lenient=True)
    assert len(list(reader)) == 204 and reader.counters["epochs_skipped"] == 1


def test_ubx_poll_form_of_a_used_message_is_counted():
    # An empty RXM-RAWX payload is a poll request; pyubx2 parses it without fields.
    mapper = UbxMapper()
    assert mapper.on_message(UBXReader.parse(reseal_ubx(b"\x02\x15"))) == []
    assert mapper.counters["ubx_poll"] == 1
    dec = StreamDecoder()
    dec.feed(reseal_ubx(b"\x01\x20") + reseal_ubx(b"\x02\x13"))
    assert dec.counters["ubx_poll"] == 2 and dec.counters["decode_errors_ubx"] == 0


@pytest.mark.parametrize("bad_pr_m", [math.inf, math.nan, -2.0e7, 1.0e300])
def test_rawx_valid_flag_with_impossible_pseudorange_is_counted_not_used(bad_pr_m):
    # A checksum-valid RAWX whose prMes is flagged valid but is no range reached the solver.
    raw = next(f for f in frames_of("RXM-RAWX") if len(f) > 400)
    clean = UBXReader.parse(raw)
    payload = bytearray(raw[6:-2])
    k = next(i for i in range(clean.numMeas) if getattr(clean, f"gnssId_{i + 1:02d}") == 3)
    payload[16 + 32 * k : 24 + 32 * k] = struct.pack("<d", bad_pr_m)
    bad = reseal_ubx(raw[2:4] + bytes(payload))
    dec = StreamDecoder()
    (epoch,) = [e for e in dec.feed(bad) + dec.flush() if isinstance(e, MeasurementEpoch)]
    assert dec.counters["rawx_pr_implausible"] == 1
    want = {
        f"C{getattr(clean, f'svId_{i + 1:02d}'):02d}": getattr(clean, f"prMes_{i + 1:02d}")
        for i in range(clean.numMeas)
        if getattr(clean, f"gnssId_{i + 1:02d}") == 3
        and getattr(clean, f"sigId_{i + 1:02d}") in (0, 1)
        and getattr(clean, f"prValid_{i + 1:02d}")
    }
    bad_prn = f"C{getattr(clean, f'svId_{k + 1:02d}'):02d}"
    for prn, pr in zip(epoch.prn, epoch.pr_m, strict=True):
        if prn == bad_prn:
            assert math.isnan(pr)
        else:
            assert pr == want[prn]


# --- Android GnssLogger logs ------------------------------------------------------------------


def _android_lines() -> list[str]:
    """Header lines and every 50th Raw row of both shared phone logs (all row kinds)."""
    out: list[str] = []
    for path in (
        DATA / "android-perth-s8-2017" / "SensorLog20171005.txt",
        DATA / "android-beijing-mi8-2022" / "gnss_log_2022_09_28_22_01_27.txt",
    ):
        lines = path.read_text().splitlines(keepends=True)
        out += [x for x in lines if x.startswith("#")]
        out += [x for x in lines if not x.startswith("#")][::50]
    out.append("Fix,GPS,39.9,116.3,50.0,0.0,3.5,1664373688500\n")
    return out


_ANDROID = _android_lines()
android_line = st.sampled_from(_ANDROID)
android_log = st.lists(
    st.one_of(
        android_line,
        android_line.flatmap(lambda x: mutated(x.encode())).map(
            lambda b: b.decode("utf-8", "replace")
        ),
        st.text(max_size=120),
    ),
    max_size=60,
)


@FUZZ
@given(android_log)
def test_gnsslogger_reader_never_raises(lines):
    """Real rows, mutated rows and random text: the reader yields epochs and receiver fixes
    only, counts what it cannot read, and never raises or hangs."""
    from drivers.gnsslogger import GnssLoggerReader

    with hang_guard():
        events = list(GnssLoggerReader(lines))
    assert all(isinstance(e, MeasurementEpoch | ReceiverFix) for e in events)


def test_a_checksum_valid_frame_nothing_can_read_is_said_not_only_counted(caplog):
    """An RXM-RAWX whose checksum holds but whose 20 bytes are no RAWX layout (pyubx2 gives
    up on its repeated group): counted ``decode_errors_ubx`` and said in a WARNING naming
    the offset and the error, once per interval (rate-limited), not only at DEBUG."""
    frame = reseal_ubx(b"\x02\x15" + bytes(range(20)))
    dec = StreamDecoder()
    with caplog.at_level("WARNING", logger="drivers.source"):
        assert dec.feed(frame + frame) == []
    assert dec.counters["decode_errors_ubx"] == 2
    said = [r.getMessage() for r in caplog.records if r.name == "drivers.source"]
    assert len(said) == 1
    assert "ubx frame at offset 0 not decoded" in said[0] and "decode_errors_ubx" in said[0]
