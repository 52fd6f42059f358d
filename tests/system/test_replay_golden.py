"""Replays of real captures against golden JSONL and NMEA (``pytest --regen-golden``).

Each golden says what it is, as gpsd's regression files do. The JSONL golden opens with a
``GOLDEN`` record: the capture and replay command, what the case checks, whether fixes are
expected, and what the source skipped (input dropped: bad bytes, resyncs, bad frames). It
closes with the run's final ``STATUS`` record (the daemon publishes it on ZeroMQ; here it is
taken from the receiver loop) without the loop timings, which vary from run to run. The NMEA
golden opens with the same two records as ``#`` comment lines.

A golden without a FIX record fails, unless its header says no fixes are expected: because
of a known defect, or because the capture holds no measurements at all (then whether its
subframes give TRACK records is stated too). Such a golden must then hold no FIX at all, so
fixing the defect fails the test until the golden is regenerated with the note removed
from :data:`CASES`.

A change to a golden file must say why in its commit. Numbers compare within the last
printed digit, so a different libm cannot fail the test while any real change does;
counters compare exactly.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass

import pytest

from service.commands.cli import main
from service.daemon.loop import Runner
from service.output.records import dumps, status_record
from tests.support.paths import DATA, GOLDEN

POSITIONED = "expected"
"""FIX records expected, some of them with a position."""
DECLINED = "expected, all declined"
"""FIX records expected, every one declined (the capture cannot give a position)."""
NO_FIXES = "no fixes: known defect "
"""No FIX record, because of the known defect named after this (and its issue)."""
SUBFRAMES_ONLY = "no fixes: no measurements in the capture; TRACK from its B1I subframes"
"""No FIX record (nothing to solve), but TRACK records: the capture's B1I subframes decode."""
GPS_GAL_SUBFRAMES_ONLY = (
    "no fixes: no measurements in the capture, and no B1I subframe (its BDS subframes are "
    "B3I D1 and B-CNAV, not mapped); TRACK from its GPS LNAV subframes and Galileo I/NAV "
    "pages"
)
"""No FIX record, and TRACK records of GPS satellites only: the capture's GPS LNAV
subframes decode (every system is selected by default), its BDS subframes are not B1I."""
NAV_ONLY = (
    "no fixes: no measurements in the capture (one empty MeasEpoch) and no B1I subframe; "
    "ephemerides and ionosphere only"
)
"""Neither FIX nor TRACK records: the capture carries navigation data only."""
NO_RECORDS = (SUBFRAMES_ONLY, GPS_GAL_SUBFRAMES_ONLY, NAV_ONLY)


@dataclass(frozen=True)
class Case:
    args: list[str]  # capture first, paths relative to ../shared/data
    checks: str
    fixes: str = POSITIONED


CASES = {
    "polyu-f9p-ubx": Case(
        [
            "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx",
            "--nav",
            "hk-polyu-f9p-ubx-2024/hksc269h.24f",
        ],
        "ZED-F9P UBX (RAWX, SFRBX D1) interleaved with NMEA, RINEX nav of the hour: an SPP "
        "fix at each of the 196 RAWX epochs, D1 subframes decoded",
    ),
    "ublox-x20p": Case(
        ["ublox-logs/ublox-x20p.log"],
        "X20P SFRBX (gpsd regression log), time from NAV-TIMEGPS: its BDS subframes are "
        "B3I D1 (sigId 4) and B-CNAV, counted as unmapped (the service decodes B1I); its GPS "
        "LNAV subframes and Galileo I/NAV pages decode",
        GPS_GAL_SUBFRAMES_ONLY,
    ),
    "ublox-zed-f9p-sfrbx": Case(
        ["ublox-logs/ublox-zed-f9p-sfrbx.log"],
        "ZED-F9P SFRBX with BDS B1I D1 subframes and no RAWX (gpsd regression log): time "
        "from NAV-TIMEGPS/NAV-PVT, a TRACK sow event per subframe",
        SUBFRAMES_ONLY,
    ),
    "ublox-zed-f9p-hpg111": Case(
        ["ublox-logs/ublox-zed-f9p_hpg1.11.log"],
        "ZED-F9P HPG 1.11 RAWX + MEASX (gpsd regression log), no ephemeris in the capture: "
        "every epoch declined (no ephemeris), TRACK events",
        DECLINED,
    ),
    "ublox-zed-f9r": Case(
        ["ublox-logs/ublox-zed-f9r.log"],
        "ZED-F9R UBX + NMEA + RTCM3 (MSM5 1125, 1042 ephemerides): declined until the "
        "ephemerides arrive, SPP fixes after",
    ),
    "hiroshima-rtcm": Case(
        ["hiroshima-oem729-rtcm-2022/20221213-010900.rtcm"],
        "NovAtel OEM729 RTCM3 (MSM7, 7 GEOs, in-stream ephemerides) without --gps-week: the "
        "week from the first ephemeris in the stream (Galileo 1045), the 6 epochs before it "
        "declined no_time, no_ephemeris until the first 1042, SPP fixes after; all 60 epochs",
    ),
    "tiny-ntrip": Case(
        ["tiny-ubx-rtcm/pygpsdata-NTRIP-USCL00CHL0.log"],
        "pyrtcm NTRIP capture (MSM 1126/1127, one 1042): one epoch, declined (too few full)",
        DECLINED,
    ),
    "tiny-rtcm3": Case(
        ["tiny-ubx-rtcm/pygpsdata-RTCM3.log", "--gps-week", "2200"],
        "pyrtcm RTCM3 capture (one BDS MSM7 1127), week given: one epoch, declined (no ephemeris)",
        DECLINED,
    ),
    "tiny-rawx": Case(
        ["tiny-ubx-rtcm/pygpsdata-RXMRAWX.log"],
        "pyubx2 RXM-RAWX capture (14 epochs), no ephemeris: every epoch declined",
        DECLINED,
    ),
    "leuven-sbf": Case(
        ["leuven-septentrio-sbf-2025/log_0000.sbf"],
        "Septentrio mosaic SBF (MeasEpoch, BDSNav, BDSIon, BDSRaw among 49 block kinds; "
        "GPS/Galileo/GLONASS counted, not used): the file's own nav blocks, which follow "
        "its first MeasEpoch, give an SPP fix at each of the 12 epochs (C05 is tracked on "
        "B2I only, so no GEO: no fast fix)",
    ),
    "leuven-sbf-all-blocks": Case(
        ["leuven-septentrio-sbf-2025/all_blocks_0000.sbf"],
        "Septentrio SBF with one of every block kind: nav blocks mapped, the rest counted by name",
        NAV_ONLY,
    ),
    "android-perth": Case(
        [
            "android-perth-s8-2017/SensorLog20171005.txt",
            "--nav",
            "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
        ],
        "Android GnssLogger start-up (Galaxy S8), mixed RINEX nav: coarse-time fixes from the "
        "first epoch (every range fractional, GPS and BeiDou rows, the phone's 5.97 s time "
        "uncertainty taken as a 29.9 s prior), SPP from 4 full GPS ranges at 12.00 s, fast "
        "fixes once a GEO joins at 83 s",
    ),
    "hksc-rinex": Case(
        ["hksc-2021/hksc1610.obs", "--nav", "hksc-2021/hksc1610.nav"],
        "HKSC 2021 RINEX 3.04 obs + nav (5 GEOs): an SPP fix at each of the 205 epochs",
    ),
}
TIMING = re.compile(r"epoch_\w+_ms")  # the loop's latency quantiles (service.daemon.loop)


def _args(parts):
    out = []
    for p in parts:
        out.append(str(DATA / p) if "/" in p else p)
    return out


def header(name: str, skipped: dict[str, int]) -> dict:
    """The ``GOLDEN`` record of a case, with what the run skipped."""
    case = CASES[name]
    return {
        "class": "GOLDEN",
        "name": name,
        "capture": case.args[0],
        "command": " ".join(["bdsfix", "replay", *case.args, "--max-speed"]),
        "checks": case.checks,
        "fixes": case.fixes,
        "skipped": skipped,
    }


def replay_summary(stderr: str) -> str:
    """The summary ``bdsfix replay`` prints at its end: its ``N epochs`` line and the
    indented lines under it (log lines before it are not part of it)."""
    lines = stderr.splitlines()
    start = next(i for i, x in enumerate(lines) if re.match(r"bdsfix replay: \d+ epochs", x))
    block = [lines[start]]
    block += [x for x in lines[start + 1 :] if x.startswith("  ")]
    return "\n".join(block) + "\n"


def read_jsonl_golden(name: str) -> tuple[dict, list[str], dict]:
    """(header, the replay's JSONL lines, final STATUS) of a JSONL golden."""
    lines = (GOLDEN / f"{name}.jsonl").read_text().splitlines()
    assert len(lines) >= 2, f"{name}.jsonl: no header and STATUS (pytest --regen-golden)"
    head, status = json.loads(lines[0]), json.loads(lines[-1])
    assert head.get("class") == "GOLDEN", f"{name}.jsonl: no GOLDEN header record"
    assert status.get("class") == "STATUS", f"{name}.jsonl: no closing STATUS record"
    return head, lines[1:-1], status


@pytest.fixture
def final_counters(monkeypatch):
    """The receiver loop's counters and skip counts when it stops (what the daemon's last
    STATUS carries), recorded from :class:`service.daemon.loop.Runner`."""
    got: dict[str, dict] = {}
    run = Runner.run

    def recording_run(self):
        try:
            return run(self)
        finally:
            got["counters"], got["skipped"] = self.counters(), self.skipped()

    monkeypatch.setattr(Runner, "run", recording_run)
    return got


def _num(text):
    try:
        return float(text)
    except ValueError:
        return None


def _close(a, b, decimals):
    return math.isclose(a, b, rel_tol=0, abs_tol=2.5 * 10.0 ** (-decimals)) if decimals else a == b


def _same_field(got: str, want: str) -> bool:
    g, w = _num(got), _num(want)
    if g is None or w is None:
        return got == want
    dec = len(want.split(".")[1]) if "." in want else 0
    return _close(g, w, dec)


def _same_json(got, want) -> bool:
    if isinstance(want, dict):
        return (
            isinstance(got, dict)
            and got.keys() == want.keys()
            and all(_same_json(got[k], want[k]) for k in want)
        )
    if isinstance(want, list):
        return len(got) == len(want) and all(
            _same_json(g, w) for g, w in zip(got, want, strict=True)
        )
    if isinstance(want, float) and isinstance(got, (int, float)):
        return math.isclose(got, want, rel_tol=1e-9, abs_tol=2e-4)
    return got == want


@pytest.mark.parametrize("name", sorted(CASES))
def test_replay_matches_golden(name, tmp_path, request, final_counters, capsys):
    jsonl, nmea = tmp_path / "out.jsonl", tmp_path / "out.nmea"
    rc = main(
        [
            "replay",
            *_args(CASES[name].args),
            "--max-speed",
            "--jsonl-out",
            str(jsonl),
            "--nmea-out",
            str(nmea),
        ]
    )
    assert rc == 0
    summary = replay_summary(capsys.readouterr().err)
    counters = {k: v for k, v in final_counters["counters"].items() if not TIMING.fullmatch(k)}
    head_line = dumps(header(name, final_counters["skipped"]))
    status_line = dumps(status_record(counters))
    g_jsonl, g_nmea = GOLDEN / f"{name}.jsonl", GOLDEN / f"{name}.nmea"
    g_summary = GOLDEN / f"{name}.summary"
    if request.config.getoption("--regen-golden"):
        GOLDEN.mkdir(exist_ok=True)
        g_summary.write_text(summary)
        g_jsonl.write_text(f"{head_line}\n{jsonl.read_text()}{status_line}\n")
        g_nmea.write_text(f"# {head_line}\n# {status_line}\n{nmea.read_text()}")
        pytest.skip("golden files regenerated")

    head, want_lines, want_status = read_jsonl_golden(name)
    # the golden names its capture, what it checks and whether fixes are expected
    assert head == json.loads(head_line), "golden header differs: regenerate and say why"
    # an empty golden passes only where its header says why no fix is expected
    fixes = [r for r in map(json.loads, want_lines) if r["class"] == "FIX"]
    positioned = [r for r in fixes if r["mode"] != "none"]
    tracks = [r for r in map(json.loads, want_lines) if r["class"] == "TRACK"]
    if head["fixes"].startswith(NO_FIXES) or head["fixes"] in NO_RECORDS:
        assert not fixes, f"{name}: FIX in a golden whose header says {head['fixes']!r}"
        if head["fixes"] in NO_RECORDS:
            with_tracks = (SUBFRAMES_ONLY, GPS_GAL_SUBFRAMES_ONLY)
            assert bool(tracks) == (head["fixes"] in with_tracks), (name, len(tracks))
            if head["fixes"] == GPS_GAL_SUBFRAMES_ONLY:
                assert {r["prn"][0] for r in tracks} == {"G", "E"}, name
    else:
        assert fixes, f"{name}: empty golden (no FIX) although its header expects fixes"
        assert head["fixes"] in (POSITIONED, DECLINED), head["fixes"]
        assert bool(positioned) == (head["fixes"] == POSITIONED), (name, len(positioned))
    # the run's final counters, skip counts included, exactly
    assert want_status == json.loads(status_line)
    # what the user reads at the end: fixes, decline reasons in words with a hint, skipped
    # input, the timeline
    assert summary == g_summary.read_text(), "replay summary differs: regenerate and say why"
    assert summary.startswith("bdsfix replay: ") and "epochs; fixes" in summary

    got = [json.loads(x) for x in jsonl.read_text().splitlines()]
    want = [json.loads(x) for x in want_lines]
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert _same_json(g, w), (i, g, w)

    g_text = g_nmea.read_text().splitlines()
    comments = [x for x in g_text if x.startswith("#")]
    assert comments == [f"# {head_line}", f"# {status_line}"], "NMEA golden header"
    got_n, want_n = nmea.read_text().splitlines(), g_text[len(comments) :]
    assert len(got_n) == len(want_n)
    for g, w in zip(got_n, want_n, strict=True):
        gf, wf = g.split("*")[0].split(","), w.split("*")[0].split(",")
        assert len(gf) == len(wf) and all(_same_field(a, b) for a, b in zip(gf, wf, strict=True)), (
            g,
            w,
        )


def test_output_kind_spec_gives_the_same_bytes_as_the_named_flags(tmp_path):
    """``--output jsonl:F --output nmea-file:G`` opens the same sinks as ``--jsonl-out F
    --nmea-out G``: byte-identical files."""
    capture = _args(CASES["tiny-rawx"].args)
    named, generic = tmp_path / "named", tmp_path / "generic"
    for d in (named, generic):
        d.mkdir()
    flags = ["--jsonl-out", str(named / "out.jsonl"), "--nmea-out", str(named / "out.nmea")]
    assert main(["replay", *capture, "--max-speed", *flags]) == 0
    outputs = ["--output", f"jsonl:{generic / 'out.jsonl'}"]
    outputs += ["--output", f"nmea-file:{generic / 'out.nmea'}"]
    assert main(["replay", *capture, "--max-speed", *outputs]) == 0
    for name in ("out.jsonl", "out.nmea"):
        assert (generic / name).read_bytes() == (named / name).read_bytes() != b""
