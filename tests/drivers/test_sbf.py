"""The Septentrio SBF driver (:mod:`drivers.sbf`) on the real Leuven mosaic captures.

Expected values come from pysbf2's own stream reader and parse (an independent reading of
the blocks), from physics (pseudorange rate against Doppler, subframe time against block
time) and from the receiver's own PVTGeodetic; none from the code under test.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import tty
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pysbf2 import SBFReader
from pysbf2.sbfhelpers import calc_crc

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from drivers.sbf import SbfMapper, meas_epoch_rows
from drivers.source import BinarySource, StreamDecoder, open_source
from drivers.transport import SerialTransport
from service.core.bds_nav import decode_word, parse_header, subframe_start_sow_s
from service.core.constants import C_M_S
from service.core.ephemeris import ephemeris_problem
from service.core.errors import DecodeError
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.types import Ephemeris, KlobucharParams, MeasurementEpoch, NavSubframe
from tests.drivers.test_fuzz_drivers import (
    EVENT_TYPES,
    FUZZ,
    feed_in_chunks,
    hang_guard,
    library_parse,
    mutated,
)
from tests.support.paths import DATA

LEUVEN = DATA / "leuven-septentrio-sbf-2025"
LOG = LEUVEN / "log_0000.sbf"
ALL_BLOCKS = LEUVEN / "all_blocks_0000.sbf"
B1I_HZ = 1561.098e6  # BDS-SIS-ICD-B1I-3.0 section 4.2
BDT_GPST_S = 14.0
CODE_MSB_M = 65.536  # MeasEpoch type-2 CodeOffsetMSB unit


def pysbf2_blocks(path: Path) -> list[tuple[bytes, object]]:
    """Every block as pysbf2's stream reader splits and parses it."""
    with open(path, "rb") as fh:
        return [(bytes(raw), msg) for raw, msg in SBFReader(fh)]


def events_of(path: Path) -> tuple[list, StreamDecoder]:
    dec = StreamDecoder()
    data = path.read_bytes()
    return dec.feed(data) + dec.flush(), dec


# --- framing ---------------------------------------------------------------------------------


@pytest.mark.parametrize("path", [LOG, ALL_BLOCKS], ids=lambda p: p.name)
def test_framer_finds_exactly_the_pysbf2_blocks(path: Path):
    want = [raw for raw, _ in pysbf2_blocks(path)]
    data = path.read_bytes()
    framer = Framer(PROTOCOLS)
    frames = framer.feed(data) + framer.flush()
    assert [f.raw for f in frames] == want
    assert {f.protocol for f in frames} == {"sbf"}
    assert framer.counters["bytes_skipped"] == 0 and sum(map(len, want)) == len(data)
    # split at every 997th byte: the same frames
    split = Framer(PROTOCOLS)
    got = [f.raw for i in range(0, len(data), 997) for f in split.feed(data[i : i + 997])]
    assert got + [f.raw for f in split.flush()] == want


def test_sbf_and_nmea_share_the_dollar_sign_and_bad_blocks_resync():
    blocks = [raw for raw, _ in pysbf2_blocks(LOG)][:40]
    nmea = b"$GPGGA,,,,,,0,,,,,,,,*66\r\n"
    bad = bytearray(blocks[3])
    bad[20] ^= 0x01  # body damaged: the CRC fails
    stream = nmea + blocks[0] + b"$@\x00garbage" + bytes(bad) + blocks[1] + nmea
    stream += b"".join(blocks[2:])
    framer = Framer(PROTOCOLS)
    frames = [f for i in range(len(stream)) for f in framer.feed(stream[i : i + 1])]
    frames += framer.flush()
    sbf = [f.raw for f in frames if f.protocol == "sbf"]
    assert sbf == [blocks[0], blocks[1], *blocks[2:]]
    assert [f.raw for f in frames if f.protocol == "nmea"] == [nmea, nmea]
    c = framer.counters
    assert c["bad_checksum_sbf"] == 1
    assert c["bytes_skipped"] == len(b"$@\x00garbage") + len(bad)


# --- MeasEpoch -------------------------------------------------------------------------------


def _pysbf2_rows(msg) -> list[tuple[int, int, float, float, float]]:
    """(SVID, signal, pseudorange, C/N0, lock time) per signal from pysbf2's MeasEpoch
    fields (type-1 then its type-2 sub-blocks), by the Reference Guide's formulas: code
    = CodeMSB + CodeLSB (type 2: + CodeOffsetMSB + CodeOffsetLSB, the MSB a signed 3-bit
    field of 65.536 m), C/N0 = CN0 + 10 dB-Hz except GPS L1P/L2P (signals 1, 2)."""
    rows = []
    for i in range(1, int(msg.N1) + 1):
        s = f"_{i:02d}"
        sig = int(getattr(msg, "SigIdxLo" + s))
        code = float(getattr(msg, "CodeMSB" + s)) + float(getattr(msg, "CodeLSB" + s))
        cn0 = float(getattr(msg, "CN0" + s)) + (0 if sig in (1, 2) else 10)
        rows.append((int(getattr(msg, "SVID" + s)), sig, code, cn0, getattr(msg, "LockTime" + s)))
        for j in range(1, int(getattr(msg, "N2" + s)) + 1):
            t = f"{s}_{j:02d}"
            sig2 = int(getattr(msg, "SigIdxLo" + t))
            msb = float(getattr(msg, "CodeOffsetMSB" + t))
            if msb >= 4 * CODE_MSB_M:  # pysbf2 reads the signed 3-bit field unsigned
                msb -= 8 * CODE_MSB_M
            off = msb + float(getattr(msg, "CodeOffsetLSB" + t))
            cn02 = float(getattr(msg, "CN0" + t)) + (0 if sig2 in (1, 2) else 10)
            rows.append(
                (
                    int(getattr(msg, "SVID" + s)),
                    sig2,
                    code + off,
                    cn02,
                    getattr(msg, "LockTime" + t),
                )
            )
    return rows


def test_meas_epoch_rows_equal_pysbf2_values():
    n_rows = 0
    for raw, msg in pysbf2_blocks(LOG):
        if msg.identity != "MeasEpoch":
            continue
        tow_ms, wnc, rows = meas_epoch_rows(raw)
        assert (tow_ms, wnc) == (int.from_bytes(raw[8:12], "little"), int(msg.WNc))
        want = _pysbf2_rows(msg)
        assert [(r[0], r[1]) for r in rows] == [(w[0], w[1]) for w in want]
        np.testing.assert_allclose([r[3] for r in rows], [w[2] for w in want], atol=1e-6)
        np.testing.assert_allclose([r[5] for r in rows], [w[3] for w in want])
        assert [r[6] for r in rows] == [float(w[4]) for w in want]
        # a satellite's codes on two carriers differ by the ionosphere and the biases:
        # metres, never the 262-524 m an unsigned offset gives
        for k, r in enumerate(rows):
            if k and rows[k - 1][0] == r[0]:
                assert abs(r[3] - rows[k - 1][3]) < 100.0
        n_rows += len(rows)
    assert n_rows > 500


def test_epochs_and_counts_against_pysbf2():
    blocks = pysbf2_blocks(LOG)
    events, dec = events_of(LOG)
    epochs = [e for e in events if isinstance(e, MeasurementEpoch)]
    measep = [m for _, m in blocks if m.identity == "MeasEpoch"]
    assert [(e.gpst_week, e.gpst_tow_s) for e in epochs] == [
        (int(m.WNc), raw_tow / 1000)
        for (raw, m) in blocks
        if m.identity == "MeasEpoch"
        for raw_tow in [int.from_bytes(raw[8:12], "little")]
    ]
    # B1I rows: signal 28 of SVIDs 141-180 / 223-245 (the Reference Guide's tables)
    for e, m in zip(epochs, measep, strict=True):
        want = sorted(
            f"C{(w[0] - 140) if w[0] <= 180 else (w[0] - 182):02d}"
            for w in _pysbf2_rows(m)
            if w[1] == 28 and (141 <= w[0] <= 180 or 223 <= w[0] <= 245)
        )
        assert list(e.prn) == want
        assert e.signal == ("2I",) * len(want) and np.all(np.isfinite(e.pr_m))
    assert min(map(len, epochs)) >= 8 and max(map(len, epochs)) <= 11
    kinds = [m.identity for _, m in blocks]
    assert sum(isinstance(e, Ephemeris) for e in events) == kinds.count("BDSNav") == 20
    assert sum(isinstance(e, KlobucharParams) for e in events) == kinds.count("BDSIon") == 1
    b1i_raw = [m for _, m in blocks if m.identity == "BDSRaw" and m.SigIdx == 28 and m.CRCPassed]
    assert sum(isinstance(e, NavSubframe) for e in events) == len(b1i_raw) == 24
    c = dec.counters
    assert c["frames_sbf"] == len(blocks) and c["decode_errors_sbf"] == 0
    assert c["epochs_sbf"] == 12 and c["sbf:MeasEpoch"] == 12


def test_b1i_doppler_matches_the_pseudorange_rate():
    """Over the 11 s of the capture, each satellite's pseudorange rate plus lambda times its
    mean Doppler is the same for all (the receiver clock drift): within 0.3 m/s. A Doppler
    offset read unsigned in a type-2 sub-block (B1I behind a B2I type-1, e.g. C08) would be
    off by tens of m/s."""
    events, _ = events_of(LOG)
    epochs = [e for e in events if isinstance(e, MeasurementEpoch)]
    first, last = epochs[0], epochs[-1]
    dt = last.gpst_tow_s - first.gpst_tow_s
    lam = C_M_S / B1I_HZ
    common = []
    for prn in set(first.prn) & set(last.prn):
        rate = (last.pr_m[last.prn.index(prn)] - first.pr_m[first.prn.index(prn)]) / dt
        dop = np.mean([e.doppler_hz[e.prn.index(prn)] for e in epochs if prn in e.prn])
        common.append(rate + lam * dop)
    assert len(common) >= 8
    assert np.ptp(common) < 0.3, common


# --- navigation ------------------------------------------------------------------------------


def _receiver_fixes() -> dict[float, np.ndarray]:
    from service.core.geometry import geodetic_to_ecef

    out = {}
    for raw, m in pysbf2_blocks(LOG):
        if m.identity == "PVTGeodetic":
            tow = int.from_bytes(raw[8:12], "little") / 1000
            out[tow] = geodetic_to_ecef(float(m.Latitude), float(m.Longitude), float(m.Height))
    return out


def test_ephemerides_put_satellites_where_the_ranges_say():
    """Orbit from the mapped BDSNav sets at each B1I transmit time, against the receiver's
    own PVTGeodetic position: pseudorange minus geometric range plus the satellite clock is
    the receiver clock (common to all) plus atmosphere; above 15 deg elevation the spread is
    under 25 m. A scale error (semicircles, t_oe units, weeks) moves satellites by km."""
    events, _ = events_of(LOG)
    ephs = {e.prn: e for e in events if isinstance(e, Ephemeris)}  # the last set of each
    for e in ephs.values():
        assert ephemeris_problem(e) is None or e.health != 0
    fixes = _receiver_fixes()
    omega_e = 7.2921150e-5  # CGCS2000 Earth rotation rate (ICD 3.2)
    for epoch in (e for e in events if isinstance(e, MeasurementEpoch)):
        rx = fixes[epoch.gpst_tow_s]
        up = rx / np.linalg.norm(rx)
        res = []
        for prn, pr in zip(epoch.prn, epoch.pr_m, strict=True):
            eph = ephs.get(prn)
            if eph is None or eph.health:
                continue
            t_bdt = epoch.gpst_tow_s - BDT_GPST_S - pr / C_M_S
            pos, clk = sat_pos_clock(EphemerisArrays.from_ephemerides([eph]), eph.week, t_bdt)
            tau = pr / C_M_S
            rot = omega_e * tau
            x, y, z = pos[0]
            sat = np.array(
                [x * math.cos(rot) + y * math.sin(rot), y * math.cos(rot) - x * math.sin(rot), z]
            )
            los = sat - rx
            rng = np.linalg.norm(los)
            assert 20e6 < np.linalg.norm(sat) < 43e6
            if np.dot(los / rng, up) > math.sin(math.radians(15)):
                res.append(pr - rng + C_M_S * clk[0])
        assert len(res) >= 5
        assert np.ptp(res) < 25.0, (epoch.gpst_tow_s, res)


def test_bdsraw_subframes_decode_and_arrive_when_they_end():
    """Each B1I subframe passes BCH(15,11,1) without a correction, and its block is time
    tagged at the end of the subframe: SOW start + 6 s (D1, ICD 5.2) + 14 s (BDT to GPST)."""
    events, _ = events_of(LOG)
    subs = [e for e in events if isinstance(e, NavSubframe)]
    assert subs
    for s in subs:
        for i, w in enumerate(s.words):
            assert decode_word(w, i == 0)[1] == 0
        head = parse_header(s.words, s.nav_type)
        assert s.nav_type == "D1"
        assert s.gpst_tow_s == subframe_start_sow_s(head, s.nav_type) + 6.0 + BDT_GPST_S


def test_iono_equals_pysbf2_and_receiver_fix_is_kept():
    blocks = pysbf2_blocks(LOG)
    ion = next(m for _, m in blocks if m.identity == "BDSIon")
    events, dec = events_of(LOG)
    (k,) = [e for e in events if isinstance(e, KlobucharParams)]
    assert k.system == "BDS"
    assert k.alpha == tuple(float(getattr(ion, f"alpha_{i}")) for i in range(4))
    assert k.beta == tuple(float(getattr(ion, f"beta_{i}")) for i in range(4))
    mapper = dec.mappers["sbf"]
    assert isinstance(mapper, SbfMapper) and mapper.receiver_fix is not None
    week, tow, xyz = mapper.receiver_fix
    assert (week, tow) == (2360, max(_receiver_fixes()))
    np.testing.assert_allclose(xyz, [4021428.57, 332891.93, 4923030.28], atol=0.1)


def test_all_blocks_capture_gives_nav_only():
    events, dec = events_of(ALL_BLOCKS)
    kinds = [m.identity for _, m in pysbf2_blocks(ALL_BLOCKS)]
    assert not any(isinstance(e, MeasurementEpoch | NavSubframe) for e in events)
    assert sum(isinstance(e, Ephemeris) for e in events) == kinds.count("BDSNav")
    assert dec.counters["frames_sbf"] == len(kinds) and dec.counters["decode_errors_sbf"] == 0
    assert dec.counters["sbf:BBSamples"] == kinds.count("BBSamples")


def test_a_live_sbf_stream_over_a_pty(tmp_path: Path):
    """The capture written into a real pty and read as ``serial:``: the same epochs."""
    want, _ = events_of(LOG)
    want_epochs = [(e.gpst_tow_s, e.prn) for e in want if isinstance(e, MeasurementEpoch)]
    data = LOG.read_bytes()
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "ttySBF"
    link.symlink_to(os.ttyname(slave))

    def write() -> None:
        with contextlib.suppress(OSError):
            for i in range(0, len(data), 4096):
                os.write(master, data[i : i + 4096])

    writer = threading.Thread(target=write, daemon=True)
    src = BinarySource(SerialTransport(str(link), 115200, timeout_s=0.05), StreamDecoder())
    got = []
    try:
        with hang_guard(60.0):
            # the writer starts once the port is open (pyserial empties the input at open,
            # so bytes written before would be lost): after the first read, which ticks
            for e in src.ticks():
                if e is None:
                    if writer.ident is None:
                        writer.start()
                    continue
                if isinstance(e, MeasurementEpoch):
                    got.append((e.gpst_tow_s, e.prn))
                    if len(got) == len(want_epochs):
                        break
    finally:
        src.close()
        os.close(master)
        os.close(slave)
        if writer.ident is not None:
            writer.join(5)
    assert got == want_epochs


def test_open_source_reads_an_sbf_file():
    with open_source(str(LOG)) as src:
        n = sum(isinstance(e, MeasurementEpoch) for e in src)
    assert n == 12 and src.counters["epochs_sbf"] == 12


# --- fuzz ------------------------------------------------------------------------------------


def reseal_sbf(block: bytes) -> bytes:
    """An SBF block around ID + body (Length recomputed, padded to 4), CRC by pysbf2."""
    ident = block[:2].ljust(2, b"\x00")
    body = block[2:]
    body += bytes(-(8 + len(body)) % 4)
    length = (8 + len(body)).to_bytes(2, "little")
    crc = calc_crc(ident + length + body).to_bytes(2, "little")
    return b"$@" + crc + ident + length + body


_REAL = [
    raw
    for raw, m in pysbf2_blocks(LOG)
    if m.identity in ("MeasEpoch", "BDSNav", "BDSIon", "BDSRaw", "PVTGeodetic")
]
_REAL = _REAL[:: max(1, len(_REAL) // 30)]
real_block = st.sampled_from(_REAL)
resealed = real_block.flatmap(lambda raw: mutated(raw[4:6] + raw[8:]).map(reseal_sbf))
sbf_stream = st.lists(
    st.one_of(st.binary(max_size=200), real_block, real_block.flatmap(mutated), resealed),
    max_size=8,
).map(b"".join)


@pytest.mark.parametrize("systems", ["C", "CGE"])
@FUZZ
@given(sbf_stream, st.lists(st.integers(0, 20000), max_size=8))
def test_stream_decoder_never_raises_on_sbf(systems, data, cuts):
    dec = StreamDecoder(mapper_options={"sbf": {"systems": frozenset(systems)}})
    events = feed_in_chunks(dec, data, cuts)
    assert all(isinstance(e, EVENT_TYPES) for e in events)
    for e in events:
        if isinstance(e, MeasurementEpoch):
            assert np.all((e.pr_m > 0) & (e.pr_m < 1e8))


@pytest.mark.parametrize("systems", ["C", "CGE"])
@FUZZ
@given(st.lists(resealed, min_size=1, max_size=6))
def test_sbf_mapper_raises_at_most_decode_error_on_blocks_pysbf2_parses(systems, frames):
    mapper = SbfMapper(systems=systems)
    for raw in frames:
        is_meas_epoch = int.from_bytes(raw[4:6], "little") & 0x1FFF == 4027  # parsed here
        if not is_meas_epoch and library_parse(SBFReader, raw) is None:
            continue  # pysbf2 refuses it: the stream decoder counts that case
        with hang_guard(), contextlib.suppress(DecodeError):
            events = mapper.on_frame(raw)
            assert all(isinstance(e, EVENT_TYPES) for e in events)
    with hang_guard():
        mapper.flush()


def test_the_first_epoch_waits_for_the_nav_blocks_of_its_second():
    """The capture opens with a MeasEpoch; its 20 BDSNav follow in the same second. The first
    epoch is emitted after them (with the second MeasEpoch), a lone one at flush."""
    blocks = [raw for raw, _ in pysbf2_blocks(LOG)]
    kinds = [m.identity for _, m in pysbf2_blocks(LOG)]
    assert kinds.index("MeasEpoch") < kinds.index("BDSNav")
    events, _ = events_of(LOG)
    first = next(i for i, e in enumerate(events) if isinstance(e, MeasurementEpoch))
    assert sum(isinstance(e, Ephemeris) for e in events[:first]) == 20
    dec = StreamDecoder()
    upto_second = kinds.index("MeasEpoch", kinds.index("MeasEpoch") + 1)
    events = dec.feed(b"".join(blocks[:upto_second]))
    assert not any(isinstance(e, MeasurementEpoch) for e in events)
    assert [type(e) for e in dec.flush()] == [MeasurementEpoch]
    assert dec.flush() == []
