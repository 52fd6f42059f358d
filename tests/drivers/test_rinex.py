"""drivers.rinex on the real RINEX 3 files in ../shared/data, cross-checked against georinex.

georinex is an independent parser. Where it cannot be used as is, the test says why:
- hk-tst-urban-2019 (1760 epochs) is compared over its first 300 epochs only (georinex
  takes ~12 s on the whole file); its epoch times are compared over the whole file.
- georinex drops a whole BDS nav record when a spare field is blank, which the 3.02
  BDS-only files do; those files are compared after writing the blank spares as zeros.
Files exercising cases the data do not contain (RINEX 3.02 ``C1I``, a leading ``X1`` type
with continuation lines, BDT time tags, event flags, 3.05 GLONASS records, damage) are
generated in tmp_path from the real files; the expected values are still georinex's
readings of the untouched originals, or numbers typed from the file text.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import inspect
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from drivers.rinex import NavData, ObsHeader, RinexObsReader, iter_obs, merge_nav, read_nav
from service.core.bds import GEO_PRNS
from service.core.errors import FramingError
from service.core.types import Ephemeris, MeasurementEpoch
from tests.support.paths import DATA

HKSC_OBS = "hksc-2021/hksc1610.obs"
TWTF_OBS = "twtf-septentrio-2023/TWTF00TWN_R_20232490000_01D_30S_MO.rnx"
TST_OBS = "hk-tst-urban-2019/COM3_190428_124409.obs"
OBS_FILES = [
    HKSC_OBS,
    "hksc-2021/20210610.klt1.ublox.f9p.obs",
    TST_OBS,
    "hk-urban-3geo-2020/rover.obs",
    "hk-polyu-f9p-ubx-2024/gnss_log_2024_09_25_15_24_49.24o",
    TWTF_OBS,
]
GEORINEX_MAX_EPOCHS = {TST_OBS: 300}
MIXED_NAV = [
    "hksc-2021/hksc1610.nav",
    "hk-urban-3geo-2020/navigation_message.nav",
    "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
]
BDS_ONLY_NAV = ["hk-tst-urban-2019/hksc1180.19b", "hk-polyu-f9p-ubx-2024/hksc269h.24f"]
GPS_EPOCH = np.datetime64("1980-01-06T00:00:00", "ns")
WEEK_S = 604800


# ---------------------------------------------------------------- georinex references


def _gpst_s(t: np.datetime64) -> float:
    """A georinex time tag (GPST calendar) as seconds since the GPS epoch."""
    return float((np.datetime64(t, "ns") - GPS_EPOCH) / np.timedelta64(1, "ns")) * 1e-9


def _b1i(path: Path) -> str:
    """The B1I code from georinex's header reading: C2I (3.03+) or else C1I (3.02)."""
    import georinex

    types = georinex.obsheader3(path)["fields"]["C"]
    return "2I" if "C2I" in types else "1I"


@functools.cache
def georinex_obs(path: Path, max_epochs: int | None = None) -> dict[float, dict[str, tuple]]:
    """{GPST seconds: {prn: (pr_m, cn0_dbhz, doppler_hz)}} for epochs with a BDS B1I range."""
    import georinex

    code = _b1i(path)
    tlim = None
    if max_epochs is not None:
        times = georinex.gettime(path)
        tlim = (times[0].astype(dt.datetime), times[max_epochs - 1].astype(dt.datetime))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = georinex.load(path, use="C", meas=[f"C{code}", f"S{code}", f"D{code}"], tlim=tlim)
    pr, cn0, dop = (ds[f"{k}{code}"].values for k in "CSD")
    svs = [str(s) for s in ds.sv.values]
    out: dict[float, dict[str, tuple]] = {}
    for i, t in enumerate(ds.time.values):
        sats = {
            svs[j]: (float(pr[i, j]), float(cn0[i, j]), float(dop[i, j]))
            for j in range(len(svs))
            if np.isfinite(pr[i, j]) and pr[i, j] > 0
        }
        if sats:
            out[_gpst_s(t)] = sats
    return out


@functools.cache
def georinex_nav(path: Path) -> list[dict]:
    """Every BDS record georinex reads from a nav file, as plain dicts."""
    import georinex

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nav = georinex.load(path, use="C")
    arrays = {k: nav[k].values for k in nav.data_vars}  # (time, sv)
    times = nav.time.values
    out = []
    for j, sv in enumerate(nav.sv.values):
        for i, t in enumerate(times):
            if math.isnan(arrays["SVclockBias"][i, j]):
                continue  # no record of this copy at this time
            rec: dict = {k: float(v[i, j]) for k, v in arrays.items()}
            rec["prn"] = str(sv)[:3]  # georinex names repeated records C06_1, C06_2, ...
            rec["epoch"] = np.datetime64(t, "s")
            out.append(rec)
    return out


def _eq(a: float, b: float, tol: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


def _ours(path: Path) -> list[MeasurementEpoch]:
    return list(RinexObsReader(path))


def _assert_matches_georinex(
    epochs: list[MeasurementEpoch], ref: dict[float, dict[str, tuple]], upto_s: float = math.inf
) -> int:
    """Every epoch georinex has with BDS B1I data is ours, with the same satellites and
    values (1e-3 m, dB-Hz, Hz); every other epoch of ours is empty. Returns #ranges."""
    keys = np.array(sorted(ref))
    seen = 0
    n = 0
    for ep in epochs:
        t = ep.gpst_week * WEEK_S + ep.gpst_tow_s
        if t > upto_s + 1e-3:
            break
        i = min(int(np.searchsorted(keys, t)), len(keys) - 1)
        near = [k for k in keys[max(i - 1, 0) : i + 1] if abs(k - t) < 2e-6]  # georinex: µs
        if not near:
            assert len(ep) == 0, (t, ep.prn)
            continue
        seen += 1
        sats = ref[float(near[0])]
        assert sorted(ep.prn) == sorted(sats), t
        for i, prn in enumerate(ep.prn):
            pr, cn0, dop = sats[prn]
            assert abs(ep.pr_m[i] - pr) <= 1e-3, (t, prn)
            assert _eq(ep.cn0_dbhz[i], cn0, 1e-3), (t, prn, "cn0")
            assert _eq(ep.doppler_hz[i], dop, 1e-3), (t, prn, "doppler")
            n += 1
    assert seen == len(ref)
    return n


# ---------------------------------------------------------------- observation files


@pytest.mark.parametrize("name", OBS_FILES)
def test_obs_epochs_and_b1i_match_georinex(name):
    import georinex

    path = DATA / name
    epochs = _ours(path)
    # every epoch line (georinex.gettime reads them all, to the millisecond, truncated)
    times = georinex.gettime(path)
    assert len(epochs) == len(times)
    for ep, t in zip(epochs, times, strict=True):
        assert -1e-6 < ep.gpst_week * WEEK_S + ep.gpst_tow_s - _gpst_s(t) < 1e-3 + 1e-6
    limit = GEORINEX_MAX_EPOCHS.get(name)
    ref = georinex_obs(path, limit)
    upto = _gpst_s(times[limit - 1]) if limit else math.inf
    assert _assert_matches_georinex(epochs, ref, upto) > 0
    code = _b1i(path)
    for ep in epochs:
        assert ep.source == "rinex"
        assert set(ep.signal) <= {code}
        assert all(re.fullmatch(r"C\d\d", p) for p in ep.prn)
        assert np.all(ep.pr_m > 0)


def test_header_fields():
    h = RinexObsReader(DATA / HKSC_OBS).header
    assert isinstance(h, ObsHeader)
    assert h.version == 3.04 and h.marker_name == "HKSC" and h.receiver_type == "LEICA GR50"
    assert h.approx_xyz_m == (-2414266.9197, 5386768.9868, 2407460.0314)
    assert h.time_system == "GPS" and h.bds_code == "2I" and h.interval_s is None
    assert h.obs_types["C"] == ("C2I", "L2I", "D2I", "S2I", "C7I", "L7I", "D7I", "S7I")
    # G spans two lines: 16 types, the last three on the continuation line
    assert len(h.obs_types["G"]) == 16 and h.obs_types["G"][-3:] == ("L5Q", "D5Q", "S5Q")
    with pytest.raises(dataclasses.FrozenInstanceError):
        h.version = 3.05  # type: ignore[misc]
    t = RinexObsReader(DATA / TWTF_OBS).header
    assert t.interval_s == 30.0 and t.marker_name == "TWTF" and t.receiver_type == "SEPT POLARX4TR"
    assert len(t.obs_types["R"]) == 16 and t.obs_types["R"][-1] == "S3Q"
    # an all-zero APPROX POSITION XYZ means unknown
    assert (
        RinexObsReader(DATA / "hksc-2021/20210610.klt1.ublox.f9p.obs").header.approx_xyz_m is None
    )


def test_b1i_code_by_version():
    """3.03 (RTKCONV) and 3.04 (Septentrio) files list C2I first for BDS."""
    assert RinexObsReader(DATA / TST_OBS).header.bds_code == "2I"
    h = RinexObsReader(DATA / TWTF_OBS).header
    assert h.bds_code == "2I" and h.obs_types["C"][0] == "C2I"


def test_obs_reader_streams():
    reader = RinexObsReader(DATA / TST_OBS)
    it = iter(reader)
    assert inspect.isgenerator(it) and inspect.isgenerator(iter_obs(DATA / TST_OBS))
    first = next(it)
    assert isinstance(first, MeasurementEpoch)
    reader.close()
    with pytest.raises(StopIteration):
        next(it)
    # two independent passes over one reader
    assert sum(1 for _ in reader) == sum(1 for _ in reader) == 1760
    assert reader.counters["epochs"] == 1 + 2 * 1760


def test_satellite_ids_written_with_a_space():
    path = DATA / TST_OBS
    text = path.read_text()
    assert "\nC 1  " in text and "\nC01 " not in text
    ids = {p for ep in RinexObsReader(path) for p in ep.prn}
    assert "C01" in ids and all(re.fullmatch(r"C\d\d", p) for p in ids)
    # every "C n" record with a C2I value (the first field) is one C0n measurement
    with_pr = sum(
        1
        for line in text.splitlines()
        if re.match(r"C \d ", line) and line[3:17].strip() and float(line[3:17]) > 0
    )
    assert with_pr == sum(sum(1 for p in ep.prn if p[1] == "0") for ep in RinexObsReader(path))


def test_urban_3geo_has_exactly_three_geos_every_epoch():
    epochs = _ours(DATA / "hk-urban-3geo-2020/rover.obs")
    assert len(epochs) == 300
    for ep in epochs:
        assert sorted(p for p in ep.prn if int(p[1:]) in GEO_PRNS) == ["C01", "C03", "C04"]


def test_hksc_has_the_five_geos_and_zero_bds_epochs_are_yielded():
    epochs = _ours(DATA / HKSC_OBS)
    assert len(epochs) == 205
    assert all({"C01", "C02", "C03", "C04", "C05"} <= set(ep.prn) for ep in epochs)
    tst = _ours(DATA / TST_OBS)
    empty = sum(1 for ep in tst if len(ep) == 0)
    # georinex (use='C') keeps only the epochs that carry BDS data
    assert empty == 1760 - 1739 and empty > 0


# ---------------------------------------------------------------- generated variants


def _lines(name: str) -> list[str]:
    return (DATA / name).read_text().splitlines(keepends=True)


def _end_of_header(lines: list[str]) -> int:
    return next(i for i, line in enumerate(lines) if "END OF HEADER" in line)


def _write(tmp_path: Path, name: str, lines: list[str]) -> Path:
    out = tmp_path / name
    out.write_text("".join(lines))
    return out


def _types_header(sys_char: str, types: list[str]) -> list[str]:
    """``SYS / # / OBS TYPES`` records, 13 types per line (A1,2X,I3,13(1X,A3))."""
    out = []
    for k in range(0, len(types), 13):
        head = f"{sys_char}  {len(types):3d}" if k == 0 else " " * 6
        body = "".join(f" {t:<3s}" for t in types[k : k + 13])
        out.append(f"{head + body:<60s}SYS / # / OBS TYPES\n")
    return out


def test_rinex_302_c1i(tmp_path):
    lines = _lines(HKSC_OBS)
    lines[0] = "     3.02" + lines[0][9:]
    i = next(k for k, line in enumerate(lines) if line.startswith("C    8 C2I"))
    lines[i] = lines[i].replace("C2I L2I D2I S2I", "C1I L1I D1I S1I")
    path = _write(tmp_path, "hksc302.obs", lines)
    reader = RinexObsReader(path)
    assert reader.header.version == 3.02 and reader.header.bds_code == "1I"
    epochs = list(reader)
    assert {s for ep in epochs for s in ep.signal} == {"1I"}
    assert _assert_matches_georinex(epochs, georinex_obs(DATA / HKSC_OBS)) > 3000


def test_version_305_obs_header_is_accepted(tmp_path):
    lines = _lines(HKSC_OBS)
    lines[0] = lines[0].replace("3.04", "3.05", 1)
    path = _write(tmp_path, "v305.obs", lines)
    eps = list(RinexObsReader(path))
    assert RinexObsReader(path).header.version == 3.05 and len(eps) == 205


def test_c2i_preferred_when_c1i_is_also_listed(tmp_path):
    lines = _lines(TWTF_OBS)
    i = next(k for k, line in enumerate(lines) if line.startswith("C    8 C2I"))
    lines[i] = lines[i].replace("C7I L7I D7I S7I", "C1I L1I D1I S1I")
    reader = RinexObsReader(_write(tmp_path, "both.rnx", lines))
    assert reader.header.bds_code == "2I"
    assert _assert_matches_georinex(list(reader), georinex_obs(DATA / TWTF_OBS)) == 50


def test_leading_x1_type_and_b1i_on_a_continuation_line(tmp_path):
    """Septentrio writes an ``X1`` (channel) type; put it first for system C with 12 more
    types so that C2I is the 14th, on the continuation line, and check we read C2I."""
    lines = _lines(TWTF_OBS)
    extra = ["X1", "C6I", "L6I", "D6I", "S6I", "C7D", "L7D", "D7D", "S7D"]
    extra += ["C5P", "L5P", "D5P", "S5P"]
    orig = ["C2I", "L2I", "D2I", "S2I", "C7I", "L7I", "D7I", "S7I"]
    end = _end_of_header(lines)
    out = []
    for k, line in enumerate(lines):
        if k < end and line.startswith("C    8 C2I"):
            out.extend(_types_header("C", extra + orig))
        elif k > end and line.startswith("C"):
            pr = float(line[3:17])
            fields = f"{7.0:14.3f}  " + f"{pr + 1234.5:14.3f}  " + " " * 16 * 11
            out.append(line[:3] + fields + line[3:])
        else:
            out.append(line)
    path = _write(tmp_path, "x1.rnx", out)
    reader = RinexObsReader(path)
    assert reader.header.obs_types["C"][0] == "X1" and reader.header.bds_code == "2I"
    epochs = list(reader)
    ref = georinex_obs(DATA / TWTF_OBS)
    assert _assert_matches_georinex(epochs, ref) == 5 * 10
    # the generated file is valid RINEX: georinex reads the same from it
    import georinex

    assert georinex.obsheader3(path)["fields"]["C"][13] == "C2I"
    assert georinex_obs(path) == ref


def test_bdt_time_tags_become_gpst(tmp_path):
    lines = _lines(HKSC_OBS)
    end = _end_of_header(lines)
    out = []
    for k, line in enumerate(lines):
        if k < end and line[60:].startswith(("TIME OF FIRST OBS", "TIME OF LAST OBS")):
            f = line.split()
            t = dt.datetime(*map(int, f[:5])) + dt.timedelta(seconds=float(f[5]) - 14)
            line = (
                f"  {t.year:4d}    {t.month:02d}    {t.day:02d}    {t.hour:02d}    "
                f"{t.minute:02d}   {t.second + t.microsecond * 1e-6:10.7f}     BDT"
            ).ljust(60) + line[60:]
        elif k > end and line.startswith(">"):
            t = dt.datetime(
                int(line[2:6]), int(line[7:9]), int(line[10:12]), int(line[13:15]), int(line[16:18])
            ) + dt.timedelta(seconds=float(line[18:29]) - 14)
            sec = t.second + t.microsecond * 1e-6
            stamp = f"{t.year:4d} {t.month:02d} {t.day:02d} {t.hour:02d} {t.minute:02d}"
            line = f"> {stamp}{sec:11.7f}{line[29:]}"
        out.append(line)
    path = _write(tmp_path, "bdt.obs", out)
    reader = RinexObsReader(path)
    assert reader.header.time_system == "BDT"
    first = next(iter(reader))
    assert first.gpst_tow_s == 4 * 86400 + 3 * 3600 + 35 * 60 + 54  # Thursday 03:35:54 GPST
    assert _assert_matches_georinex(list(reader), georinex_obs(DATA / HKSC_OBS)) > 3000


def _event(flag: int, records: list[str], when: str | None = None) -> list[str]:
    head = f"> {when}" if when else ">"
    return [f"{head:<31s}{flag:1d}{len(records):3d}\n", *records]


def test_event_flags_special_records_and_redefined_types(tmp_path):
    lines = _lines(HKSC_OBS)
    end = _end_of_header(lines)
    epoch_at = [k for k in range(end + 1, len(lines)) if lines[k].startswith(">")]
    comment = f"{'inserted by test_rinex':<60s}COMMENT\n"
    marker = f"{'HKSC':<60s}MARKER NAME\n"
    new_c = ["S2I", "D2I", "L2I", "C2I", "S7I", "D7I", "L7I", "C7I"]
    perm = [3, 2, 1, 0, 7, 6, 5, 4]  # new field k comes from original field perm[k]
    inserts = {
        3: _event(4, [comment, marker]),  # header records, blank time
        10: _event(5, [], "2021 06 10 03 36 03.5000000"),  # external event, with time
        15: _event(3, [marker]),  # new site occupation, blank time
        20: _event(2, [], "2021 06 10 03 36 14.0000000"),  # start moving antenna
        100: _event(4, [comment, *_types_header("C", new_c)]),
    }
    out = lines[: end + 1]
    for n, start in enumerate(epoch_at):
        stop = epoch_at[n + 1] if n + 1 < len(epoch_at) else len(lines)
        out.extend(inserts.get(n, []))
        block = lines[start:stop]
        if n == 30:  # power failure before this epoch: still observations
            block[0] = block[0][:31] + "1" + block[0][32:]
        if n >= 100:
            for i, rec in enumerate(block[1:], start=1):
                if rec.startswith("C"):
                    body = rec.rstrip("\n").ljust(3 + 16 * 8)
                    fields = [body[3 + 16 * j : 19 + 16 * j] for j in range(8)]
                    block[i] = rec[:3] + "".join(fields[p] for p in perm).rstrip() + "\n"
        out.extend(block)
        if n == 40:  # cycle-slip records (same layout as observations, C satellites)
            out.extend(_event(6, [r for r in block[1:] if r.startswith("C")][:2], block[0][2:29]))
    path = _write(tmp_path, "events.obs", out)
    reader = RinexObsReader(path)
    epochs = list(reader)
    assert len(epochs) == 205
    assert _assert_matches_georinex(epochs, georinex_obs(DATA / HKSC_OBS)) > 3000
    c = reader.counters
    assert (c["event_flag_2"], c["event_flag_3"], c["event_flag_4"], c["event_flag_5"]) == (
        1,
        1,
        2,
        1,
    )
    assert c["special_records"] == 2 + 1 + 2 and c["cycle_slip_records"] == 2
    assert c["epochs_power_failure"] == 1 and c["epochs"] == 205


# ---------------------------------------------------------------- errors


def test_damaged_epoch_line_names_file_and_line(tmp_path):
    lines = _lines(HKSC_OBS)
    target = [k for k, line in enumerate(lines) if line.startswith(">")][10]
    lines[target] = lines[target].replace("2021 06 10", "2021 06 1x")
    path = _write(tmp_path, "hksc1610.obs", lines)
    got = []
    with pytest.raises(FramingError) as exc:
        for ep in RinexObsReader(path):
            got.append(ep)
    assert str(exc.value).startswith(f"{path}:{target + 1}: bad epoch line")
    assert "hksc1610.obs:" in str(exc.value)
    assert len(got) == 10  # streamed: the epochs before the damage came out


def test_damaged_records_name_their_line(tmp_path):
    lines = _lines(HKSC_OBS)
    c_rec = next(k for k, line in enumerate(lines) if line.startswith("C01"))
    bad = lines.copy()
    bad[c_rec] = "C01  2x0 .1234.567" + bad[c_rec][18:]
    with pytest.raises(FramingError, match=rf"bad\.obs:{c_rec + 1}: bad observation record"):
        list(RinexObsReader(_write(tmp_path, "bad.obs", bad)))
    # an epoch line announcing one record too many swallows the next epoch line
    first = next(k for k, line in enumerate(lines) if line.startswith(">"))
    more = lines.copy()
    n = int(more[first][32:35])
    more[first] = f"{more[first][:32]}{n + 1:3d}{more[first][35:]}"
    with pytest.raises(FramingError, match=rf"more\.obs:{first + n + 2}: expected an observation"):
        list(RinexObsReader(_write(tmp_path, "more.obs", more)))
    cut = _write(tmp_path, "cut.obs", lines[: first + 5])
    with pytest.raises(FramingError, match=rf"cut\.obs:{first + 5}: file ends inside the epoch"):
        list(RinexObsReader(cut))


def _repeat_geo_records(lines: list[str], shift_m: float = 0.0) -> tuple[list[str], int]:
    """``lines`` with the GEO records (C01-C05) of every epoch written again at the end of
    the epoch, the epoch line's count raised to match (the reviewer's
    rx_dup_geo_lines.obs), the repeat's pseudorange ``shift_m`` larger; and how many
    records were repeated."""
    out: list[str] = []
    repeated = 0
    k = _end_of_header(lines) + 1
    out += lines[:k]
    while k < len(lines):
        head, n = lines[k], int(lines[k][32:35])
        body = lines[k + 1 : k + 1 + n]
        again = [r for r in body if r[:3] in {f"C{p:02d}" for p in range(1, 6)}]
        if shift_m:
            again = [f"{r[:3]}{float(r[3:17]) + shift_m:14.3f}{r[17:]}" for r in again]
        out += [f"{head[:32]}{n + len(again):3d}{head[35:]}", *body, *again]
        repeated += len(again)
        k += 1 + n
    return out, repeated


@pytest.mark.parametrize("lenient", [False, True], ids=["strict", "lenient"])
def test_a_repeated_satellite_record_is_one_measurement_the_first(tmp_path, lenient):
    """hksc1610.obs with each epoch's GEO records written twice (solved as independent
    measurements they had made n_full 5 -> 10 GEO rows): both readers give the original's
    epochs, row for row, the first record kept even when the repeat says another range
    (+1 km), the repeats counted ``duplicate_records``."""
    lines = _lines(HKSC_OBS)
    clean = list(RinexObsReader(DATA / HKSC_OBS, lenient=lenient, systems="CGE"))
    for shift_m in (0.0, 1000.0):
        damaged, repeated = _repeat_geo_records(lines, shift_m)
        reader = RinexObsReader(
            _write(tmp_path, f"dup{shift_m:g}.obs", damaged), lenient=lenient, systems="CGE"
        )
        epochs = list(reader)
        assert repeated == 5 * len(clean) == reader.counters["duplicate_records"]
        assert reader.counters["bds_measurements"] == sum(p[0] == "C" for e in clean for p in e.prn)
        assert len(epochs) == len(clean)
        for a, b in zip(epochs, clean, strict=True):
            assert (a.gpst_week, a.gpst_tow_s, a.prn, a.signal) == (
                b.gpst_week,
                b.gpst_tow_s,
                b.prn,
                b.signal,
            )
            for name in ("pr_m", "frac_pr_m", "cn0_dbhz", "doppler_hz"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_not_rinex3_no_end_of_header_wrong_type(tmp_path):
    v2 = tmp_path / "old.obs"
    v2.write_text(
        f"{'     2.11           OBSERVATION DATA    M (MIXED)':<60s}RINEX VERSION / TYPE\n"
    )
    with pytest.raises(FramingError, match=r"old\.obs:1: RINEX version 2\.11 is not 3\.xx"):
        RinexObsReader(v2)
    lines = _lines(HKSC_OBS)
    end = _end_of_header(lines)
    noend = _write(tmp_path, "noend.obs", lines[:end])
    with pytest.raises(FramingError, match=rf"noend\.obs:{end}: no END OF HEADER"):
        RinexObsReader(noend)
    with pytest.raises(FramingError, match=r"file type 'N', expected 'O'"):
        RinexObsReader(DATA / MIXED_NAV[0])
    for capture in ("pygpsdata-RTCM3.log", "pygpsdata-RXMRAWX.log"):  # RTCM3, UBX
        with pytest.raises(FramingError, match="not a RINEX file"):
            read_nav(DATA / "tiny-ubx-rtcm" / capture)
    crx = tmp_path / "x.crx"
    crx.write_text(f"{'1.0                 COMPACT RINEX FORMAT':<60s}CRINEX VERS   / TYPE\n")
    with pytest.raises(FramingError, match=r"x\.crx: cannot decompress \(gzip/\.Z/Hatanaka\)"):
        RinexObsReader(crx)  # a truncated compact RINEX
    with pytest.raises(FramingError, match="cannot read"):
        read_nav(tmp_path / "missing.nav")


def test_damaged_nav_record_names_its_line(tmp_path):
    lines = _lines(BDS_ONLY_NAV[0])
    c = next(k for k, line in enumerate(lines) if line.startswith("C05"))
    bad = lines.copy()
    bad[c + 2] = bad[c + 2][:10] + "x" + bad[c + 2][11:]
    with pytest.raises(FramingError, match=rf"bad\.19b:{c + 3}: bad BDS record for C05"):
        read_nav(_write(tmp_path, "bad.19b", bad))
    short = lines[: c + 1] + lines[c + 2 :]  # one line missing from the C05 record
    with pytest.raises(FramingError, match=rf"short\.19b:{c + 1}: BDS record 'C05' has 7 lines"):
        read_nav(_write(tmp_path, "short.19b", short))


def test_non_finite_float_field_is_passed_on_a_blank_one_is_not(tmp_path):
    """The parser reads numbers; the store judges them (service.core.ephemeris)."""
    lines = _lines(BDS_ONLY_NAV[0])
    c = next(k for k, line in enumerate(lines) if line.startswith("C05"))
    sqrt_a = slice(4 + 3 * 19, 4 + 4 * 19)  # BROADCAST ORBIT - 2, fourth field
    e = slice(4 + 19, 4 + 2 * 19)  # BROADCAST ORBIT - 2, second field
    for name, text, cut, want in [
        ("nan.19b", "NaN", sqrt_a, ("sqrt_a_sqrt_m", math.isnan)),
        ("inf.19b", " .100000000000D+999", e, ("e", lambda v: v == math.inf)),
    ]:
        bad = lines.copy()
        row = bad[c + 2]
        bad[c + 2] = row[: cut.start] + text.rjust(19) + row[cut.stop :]
        nav = read_nav(_write(tmp_path, name, bad))
        ref = read_nav(DATA / BDS_ONLY_NAV[0])
        got = {p: [getattr(x, want[0]) for x in v] for p, v in nav.ephemerides.items()}
        assert want[1](got["C05"][0]) and len(got) == len(ref.ephemerides)
        assert nav.ephemerides["C06"] == ref.ephemerides["C06"]
    bad = lines.copy()
    bad[c + 2] = bad[c + 2][: sqrt_a.start] + " " * 19 + bad[c + 2][sqrt_a.stop :]
    with pytest.raises(FramingError, match=r"blank\.19b:\d+: BDS record for C05 lacks sqrt_a"):
        read_nav(_write(tmp_path, "blank.19b", bad))


def test_a_non_finite_integer_field_is_a_framing_error_naming_it(tmp_path):
    """An integer field (week, AODE) that reads as NaN or infinity has no integer value: the
    record is refused by the parser, with the file, line and field named."""
    lines = _lines(BDS_ONLY_NAV[0])
    c = next(k for k, line in enumerate(lines) if line.startswith("C05"))
    week = slice(4 + 2 * 19, 4 + 3 * 19)  # BROADCAST ORBIT - 5, third field
    aode = slice(4, 4 + 19)  # BROADCAST ORBIT - 1, first field
    for name, row, cut, text, said in [
        ("week.19b", 5, week, "NaN", "week is nan"),
        ("aode.19b", 1, aode, " .100000000000D+999", "aode is inf"),
    ]:
        bad = lines.copy()
        bad[c + row] = bad[c + row][: cut.start] + text.rjust(19) + bad[c + row][cut.stop :]
        with pytest.raises(FramingError, match=rf"{name}:{c + 1}: BDS record for C05: {said}"):
            read_nav(_write(tmp_path, name, bad))


# ---------------------------------------------------------------- navigation files

FIELDS = {  # georinex name -> ours
    "SVclockBias": "af0_s",
    "SVclockDrift": "af1_s_s",
    "SVclockDriftRate": "af2_s_s2",
    "AODE": "aode",
    "Crs": "crs_m",
    "DeltaN": "delta_n_rad_s",
    "M0": "m0_rad",
    "Cuc": "cuc_rad",
    "Eccentricity": "e",
    "Cus": "cus_rad",
    "sqrtA": "sqrt_a_sqrt_m",
    "Toe": "toe_sow_s",
    "Cic": "cic_rad",
    "Omega0": "omega0_rad",
    "Cis": "cis_rad",
    "Io": "i0_rad",
    "Crc": "crc_m",
    "omega": "omega_rad",
    "OmegaDot": "omega_dot_rad_s",
    "IDOT": "idot_rad_s",
    "BDTWeek": "week",
    "SVacc": "ura_m",
    "SatH1": "health",
    "TGD1": "tgd1_s",
    "TGD2": "tgd2_s",
    "AODC": "aodc",
}


def _zero_blank_spares(src: Path, dst: Path) -> Path:
    """Write blank 19-character fields of record lines as zeros (only spares are blank)."""
    lines = src.read_text().splitlines(keepends=True)
    end = _end_of_header(lines)
    out = lines[: end + 1]
    for line in lines[end + 1 :]:
        if line.startswith("    "):
            body = line.rstrip("\n").ljust(80)
            fields = [body[4 + 19 * j : 23 + 19 * j] for j in range(4)]
            line = "    " + "".join(f if f.strip() else " 0.000000000000D+00" for f in fields)
            line += "\n"
        out.append(line)
    dst.write_text("".join(out))
    return dst


def _compare_nav(ours: NavData, ref: list[dict]) -> int:
    """Every BDS set georinex reads equals ours field by field (exact: same text)."""
    latest: dict[tuple[str, int, float], dict] = {}
    for rec in ref:  # a set sent more than once: the latest transmission wins
        key = (rec["prn"], int(rec["BDTWeek"]), rec["Toe"])
        if key not in latest or rec["TransTime"] > latest[key]["TransTime"]:
            latest[key] = rec
    mine = {(e.prn, e.week, e.toe_sow_s): e for v in ours.ephemerides.values() for e in v}
    assert mine.keys() == latest.keys()
    for key, rec in latest.items():
        e = mine[key]
        assert isinstance(e, Ephemeris) and e.source == "rinex"
        for g, name in FIELDS.items():
            assert getattr(e, name) == rec[g], (key, name)
        # toc: the record's BDT calendar epoch as seconds of the BDT week
        day = rec["epoch"].astype("datetime64[D]")
        days = int((day - np.datetime64("2006-01-01")).astype(int))
        sod = int((rec["epoch"] - day).astype(int))
        assert e.toc_sow_s == (days % 7) * 86400 + sod, key
    return len(latest)


@pytest.mark.parametrize("name", MIXED_NAV)
def test_mixed_nav_matches_georinex(name):
    path = DATA / name
    ours = read_nav(path)
    assert _compare_nav(ours, georinex_nav(path)) == sum(map(len, ours.ephemerides.values()))


@pytest.mark.parametrize("name", BDS_ONLY_NAV)
def test_bds_only_302_nav_matches_georinex(name, tmp_path):
    path = DATA / name
    copy = _zero_blank_spares(path, tmp_path / path.name)
    ours = read_nav(path)
    assert ours.version == 3.02 and read_nav(copy).ephemerides == ours.ephemerides
    assert _compare_nav(ours, georinex_nav(copy)) > 50


def test_nav_literal_record_run_together_fields():
    """C01 of hksc1180.19b, typed from the file: numbers run together, D exponents."""
    nav = read_nav(DATA / "hk-tst-urban-2019/hksc1180.19b")
    (c01,) = [e for e in nav.ephemerides["C01"] if e.toe_sow_s == 6.012000000000e05]
    assert (c01.af0_s, c01.af1_s_s, c01.af2_s_s2) == (5.142397712916e-04, 4.822720001130e-11, 0.0)
    assert (c01.aode, c01.crs_m, c01.delta_n_rad_s, c01.m0_rad) == (
        1,
        3.683125000000e02,
        -2.525105236018e-09,
        -2.795258832287e00,
    )
    assert (c01.i0_rad, c01.crc_m, c01.omega_rad) == (
        1.099186642221e-01,
        1.714062500000e01,
        2.199281951138e00,
    )
    assert c01.idot_rad_s == -9.214669305369e-11 and c01.week == 694
    assert (c01.ura_m, c01.health, c01.tgd1_s, c01.tgd2_s) == (
        2.0,
        0,
        1.420000028673e-08,
        -1.039999997232e-08,
    )
    assert c01.toc_sow_s == 6 * 86400 + 23 * 3600  # Saturday 23:00 BDT


def test_bds_only_302_nav_literal_record():
    """georinex reads no BDS record from 3.02 BDS-only files as they are; check one against
    its text: C01 2024 09 25 06:00:00, af0 9.253375465050D-04, af1 2.944311461306D-12."""
    nav = read_nav(DATA / "hk-polyu-f9p-ubx-2024/hksc269h.24f")
    c01 = min(nav.ephemerides["C01"], key=lambda e: e.toc_sow_s)
    assert c01.af0_s == 9.253375465050e-04 and c01.af1_s_s == 2.944311461306e-12
    assert c01.toc_sow_s == 3 * 86400 + 6 * 3600  # Wednesday 06:00 BDT
    assert len(nav.ephemerides) == 50 and nav.iono_bds is not None


def test_toc_from_the_bdt_epoch_equals_toe():
    """BDS broadcasts toc = toe; reading the record epoch as GPST would miss by 14 s."""
    n = 0
    for name in MIXED_NAV + BDS_ONLY_NAV:
        for items in read_nav(DATA / name).ephemerides.values():
            for e in items:
                assert e.toc_sow_s == e.toe_sow_s
                n += 1
    assert n > 800


def test_nav_record_counts_by_system():
    """Other systems are skipped with their own line counts: the record-start lines found by
    a pattern match the reader's counts, and 8/4-line records add up to the file's lines."""
    for name in MIXED_NAV:
        lines = _lines(name)
        end = _end_of_header(lines)
        starts: dict[str, int] = {}
        for line in lines[end + 1 :]:
            m = re.match(r"([GRECJSI])[ \d]\d \d{4} [ \d]\d ", line)
            if m:
                starts[m[1]] = starts.get(m[1], 0) + 1
        per = {"G": 8, "E": 8, "J": 8, "C": 8, "I": 8, "R": 4, "S": 4}
        assert end + 1 + sum(per[s] * n for s, n in starts.items()) == len(lines)
        counters = read_nav(DATA / name).counters
        assert {s: counters[f"records_{s}"] for s in starts} == starts
        assert not any("odd_length" in k for k in counters)


def test_rinex_305_glonass_five_line_records(tmp_path):
    src = MIXED_NAV[0]
    lines = _lines(src)
    lines[0] = "     3.05" + lines[0][9:]
    out = []
    pending = 0
    for line in lines:
        out.append(line)
        if re.match(r"R\d\d \d{4}", line):
            pending = 3
        elif pending:
            pending -= 1
            if pending == 0:  # 3.05 line 5: status flags, L1/L2 delay, URAI, health flags
                out.append("    " + " 0.000000000000D+00" * 4 + "\n")
    path = _write(tmp_path, "v305.nav", out)
    nav = read_nav(path)
    orig = read_nav(DATA / src)
    assert nav.version == 3.05 and nav.ephemerides == orig.ephemerides
    assert nav.counters["records_R"] == orig.counters["records_R"] == 154
    assert not any("odd_length" in k for k in nav.counters)
    # a 3.05 file whose writer left the GLONASS records at 4 lines: counted, still read
    lines[0] = "     3.05" + lines[0][9:]
    old = read_nav(_write(tmp_path, "v305old.nav", lines))
    assert old.ephemerides == orig.ephemerides and old.counters["records_R_odd_length"] == 154


ALPHA_LSB = (2.0**-30, 2.0**-27, 2.0**-24, 2.0**-24)  # BDS-SIS-ICD 5.2.4.7, IS-GPS-200
BETA_LSB = (2.0**11, 2.0**14, 2.0**16, 2.0**16)


def assert_print(values, printed):
    """The header's printed coefficients, read back as their broadcast values: each a whole
    LSB, within the print's 4-5 digits of it."""
    lsb = ALPHA_LSB if abs(printed[0]) < 1.0 else BETA_LSB
    assert values == pytest.approx(printed, rel=1e-3, abs=1e-12)
    assert all((v / q).is_integer() for v, q in zip(values, lsb, strict=True))


def test_iono_and_leap_seconds_literal_header_values():
    nav = read_nav(DATA / "hksc-2021/hksc1610.nav")
    assert nav.iono_bds is not None and nav.iono_gps is not None
    assert nav.iono_bds.system == "BDS" and nav.iono_gps.system == "GPS"
    assert_print(nav.iono_bds.alpha, (0.9313e-08, 0.4470e-07, -0.3576e-06, 0.5961e-06))
    assert_print(nav.iono_bds.beta, (0.1188e06, 0.1638e06, -0.3277e06, 0.1966e06))
    assert_print(nav.iono_gps.alpha, (0.5588e-08, 0.1490e-07, -0.5961e-07, -0.1192e-06))
    assert_print(nav.iono_gps.beta, (0.8397e05, 0.9830e05, -0.6554e05, -0.5243e06))
    assert nav.leap_seconds == 18 and nav.version == 3.04
    tst = read_nav(DATA / "hk-tst-urban-2019/hksc1180.19b")
    assert tst.iono_bds is not None and tst.iono_gps is None
    assert_print(tst.iono_bds.alpha, (9.3132e-09, 8.9407e-08, -1.0133e-06, 2.0862e-06))
    assert_print(tst.iono_bds.beta, (1.2493e05, -6.8813e05, 6.8813e06, -7.4056e06))
    # "     4     4   573     6": BDT - UTC = 4 s in a BDS-only file, i.e. GPST - UTC = 18 s
    assert tst.leap_seconds == 18
    urban = read_nav(DATA / "hk-urban-3geo-2020/navigation_message.nav")
    assert urban.iono_bds is not None
    assert_print(urban.iono_bds.alpha, (0.1397e-07, -0.3725e-07, -0.1192e-06, 0.2384e-06))
    assert_print(urban.iono_bds.beta, (0.1004e06, -0.1475e06, 0.5898e06, 0.1966e06))
    perth = read_nav(DATA / "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx")
    assert perth.iono_bds is None and perth.iono_gps is not None
    assert_print(perth.iono_gps.alpha, (0.1024e-07, 0.7451e-08, -0.5960e-07, -0.5960e-07))


def test_repeated_sets_keep_the_latest_transmission():
    # PERT: C11 toe 370800 is sent with SatH1 0 and again, later, with SatH1 1
    perth = read_nav(DATA / "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx")
    (c11,) = [e for e in perth.ephemerides["C11"] if e.toe_sow_s == 370800.0]
    assert c11.health == 1
    for items in perth.ephemerides.values():
        keys = [(e.week, e.toe_sow_s) for e in items]
        assert keys == sorted(set(keys))


def test_merge_nav():
    tst = read_nav(DATA / "hk-tst-urban-2019/hksc1180.19b")
    perth = read_nav(DATA / "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx")
    both = merge_nav(perth, tst)
    assert both.iono_gps == perth.iono_gps and both.iono_bds == tst.iono_bds
    assert set(both.ephemerides) == set(perth.ephemerides) | set(tst.ephemerides)
    assert sum(map(len, both.ephemerides.values())) == sum(
        map(len, perth.ephemerides.values())
    ) + sum(map(len, tst.ephemerides.values()))
    assert merge_nav(tst, tst).ephemerides == tst.ephemerides
