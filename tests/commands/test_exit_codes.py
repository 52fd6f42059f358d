"""The README's exit-code table, command by command, on the real console script: an input
that cannot be used is 3 (a GPS-only nav file, an output in a missing directory), a bad
value is 2 (out-of-range position, no trials); outputs written after long work are
checked before it starts."""

from __future__ import annotations

import gzip
import signal
import subprocess
import sys

import numpy as np
import pytest

from service.core.declines import NO_EPOCHS
from tests.support.paths import DATA, ROOT

GPS_NAV = str(DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24n")  # RINEX 3, GPS only
HKSC_OBS = str(DATA / "hksc-2021" / "hksc1610.obs")
HKSC_NAV = str(DATA / "hksc-2021" / "hksc1610.nav")
MISSING = "/nonexistent-dir/out"
TWTF_OBS = str(DATA / "twtf-septentrio-2023" / "TWTF00TWN_R_20232490000_01D_30S_MO.rnx")
POLYU_UBX = str(DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx")
# the HKSC nav holds BDS sets of 2021-06-09/10; TWTF observed 2023-09-06 (day 249, from its
# name), the PolyU F9P 2024-09-25 from 07:25 UTC (the data's README)
NAV_2021_OBS_2023 = "of 2021-06-09 to 2021-06-10 (GPST), but the observations start 2023-09-06"
NAV_2021_UBX_2024 = "of 2021-06-09 to 2021-06-10 (GPST), but the observations start 2024-09-25"
RUN_QUIET = ("--state-dir", "/dev/null/state", "--nmea-tcp", "", "--zmq", "")


def _bdsfix(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.parametrize(
    ("args", "code", "says"),
    [
        (("solve", HKSC_OBS, GPS_NAV), 3, "no usable BDS ephemeris"),
        (("replay", HKSC_OBS, "--nav", GPS_NAV, "--max-speed"), 3, "no usable BDS ephemeris"),
        (("run", "--source", HKSC_OBS, "--nav", GPS_NAV, *RUN_QUIET), 3, "no usable BDS"),
        (("solve", TWTF_OBS, HKSC_NAV), 3, NAV_2021_OBS_2023),
        # GPS alone asked for, a GPS nav of another day: the hint names GPS, not BeiDou
        (("solve", HKSC_OBS, GPS_NAV, "--systems", "G"), 3, "a RINEX 3 nav file with 'G' rec"),
        (("replay", TWTF_OBS, "--nav", HKSC_NAV, "--max-speed"), 3, NAV_2021_OBS_2023),
        (("run", "--source", TWTF_OBS, "--nav", HKSC_NAV, *RUN_QUIET), 3, NAV_2021_OBS_2023),
        (("run", "--source", POLYU_UBX, "--nav", HKSC_NAV, *RUN_QUIET), 3, NAV_2021_UBX_2024),
        (("ttff", HKSC_OBS, GPS_NAV), 3, "no usable BDS ephemeris"),
        (("simulate", "--nav", GPS_NAV, "--out", "/dev/null"), 3, "no healthy BDS ephemeris"),
        (("coverage", "--nav", GPS_NAV, "--no-progress"), 3, "no GEO ephemerides"),
        (("solve", HKSC_OBS, HKSC_NAV, "--out", MISSING), 3, "cannot write"),
        (("simulate", "--out", MISSING), 3, "cannot write"),
        (("coverage", "--json", MISSING + ".json", "--no-progress"), 3, "no such directory"),
        (("coverage", "--plot", MISSING + ".png", "--no-progress"), 3, "no such directory"),
        (("ttff", HKSC_OBS, HKSC_NAV, "--plot", MISSING + ".png"), 3, "no such directory"),
        (("ttff", HKSC_OBS, HKSC_NAV, "--trials", "0"), 2, "--trials must be at least 1"),
        (("ttff", HKSC_OBS, HKSC_NAV, "--trials", "-3"), 2, "--trials must be at least 1"),
        (("simulate", "--lat-deg", "200", "--out", "/dev/null"), 2, "--lat-deg must be in"),
        (("simulate", "--lon-deg", "-400", "--out", "/dev/null"), 2, "--lon-deg must be in"),
        (("replay", "--elmask-deg", "95", "--max-speed"), 2, "elmask_deg"),
        (("run", "--elmask-deg", "95", "--source", HKSC_OBS), 2, "elmask_deg"),
        (("configure",), 2, "no receiver: give --source"),
        (("configure", "--source", "/nonexistent-dir/ttyX"), 3, "no such device"),
        (("configure", "--source", "tcp:127.0.0.1:9"), 2, "needs a serial device"),
        (("configure", "--source", HKSC_OBS), 2, "needs a serial device"),
        (("configure", "--dry-run", "--rate-hz", "0"), 2, "rate_hz"),
        (("configure", "--dry-run", "--model", "m9"), 2, "invalid choice"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, tuple) else None,
)
def test_exit_code_and_one_line(args, code, says):
    out = _bdsfix(*args)
    assert out.returncode == code, (out.returncode, out.stderr[-500:])
    lines = [ln for ln in out.stderr.splitlines() if "error:" in ln]
    assert len(lines) == 1 and says in lines[0], out.stderr[-500:]
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 0)])
def test_replay_stops_cleanly_on_a_signal_with_the_table_code(sig, code):
    """Ctrl-C is 130 and SIGTERM 0; both stop cleanly: the summary is still printed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "replay", "--speed", "1"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().startswith("$")  # it is publishing NMEA
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, err[-500:]
    assert "bdsfix replay:" in err and "epochs; fixes" in err and "Traceback" not in err


@pytest.mark.parametrize("kind", ["empty", "random", "text", "gzip"])
@pytest.mark.parametrize("command", ["replay", "run"])
def test_a_file_with_nothing_to_read_is_an_input_error(tmp_path, command, kind):
    """Empty, random, text or compressed: exit 3 with one line saying what was expected."""
    rng = np.random.default_rng(3)
    content = {
        "empty": b"",
        "random": bytes(b for b in rng.integers(0, 256, 20_000, dtype=np.uint8) if b != 0xB5),
        "text": b"hello, this is not a receiver capture\n" * 100,
        "gzip": gzip.compress(b"\xb5\x62" * 1000),
    }[kind]
    path = tmp_path / f"capture.{kind}"
    path.write_bytes(content)
    args = [command, str(path)] if command == "replay" else [command, "--source", str(path)]
    if command == "run":
        args += ["--state-dir", str(tmp_path / "state"), "--nmea-tcp", "", "--zmq", ""]
    out = _bdsfix(*args)
    assert out.returncode == 3, (out.returncode, out.stderr)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    expected = "decompress it first" if kind == "gzip" else "expected a capture of UBX"
    assert expected in lines[0]


PERTH = DATA / "android-perth-s8-2017"


def _header_only(path):
    """The HKSC RINEX 3.04 obs file up to END OF HEADER: every header record (C2I among its
    BDS observation types), no epoch."""
    text = (DATA / "hksc-2021" / "hksc1610.obs").read_text()
    path.write_text(text[: text.index("END OF HEADER")] + "END OF HEADER\n")
    return path


def _without_raw_rows(path):
    """The Perth GnssLogger log without its Raw rows (its header comments stay)."""
    lines = (PERTH / "SensorLog20171005.txt").read_text().splitlines(keepends=True)
    path.write_text("".join(ln for ln in lines if not ln.startswith("Raw,")))
    return path


@pytest.mark.parametrize(
    ("make", "nav"),
    [
        (_header_only, HKSC_NAV),
        (_without_raw_rows, str(PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx")),
    ],
    ids=["rinex-header-only", "gnsslogger-without-raw"],
)
@pytest.mark.parametrize("command", ["solve", "replay"])
def test_a_readable_file_without_epochs_ends_with_the_no_epoch_hint(tmp_path, make, nav, command):
    """A file bdsfix reads that holds no measurement epoch (a RINEX obs file with a complete
    header and no epoch record, a GnssLogger log without Raw rows) is not an input error:
    exit 0, no output, and the summary's "0 epochs" with the command's no-epoch hint, as for
    an SBF capture with an empty MeasEpoch (tests/golden/leuven-sbf-all-blocks.summary).
    Only a file with nothing bdsfix reads at all is exit 3 (above). The solve hint says what
    is missing (before: "it needs BDS pseudoranges (C2I or C1I)", though the header-only
    file's header lists C2I)."""
    path = make(tmp_path / "input")
    args = [command, str(path), nav] if command == "solve" else [command, str(path)]
    if command == "replay":
        args += ["--nav", nav, "--max-speed"]
    out = _bdsfix(*args)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout == ""
    assert "error:" not in out.stderr and "Traceback" not in out.stderr
    lines = out.stderr.splitlines()
    summary = next(ln for ln in lines if ln.startswith(f"bdsfix {command}: 0 epochs"))
    assert summary in (f"bdsfix {command}: 0 epochs", f"bdsfix {command}: 0 epochs; fixes fast"
                       " 0, spp 0, none 0; integrity checks 0, failures 0")  # fmt: skip
    assert f"  {NO_EPOCHS[command]}" in lines
    if command == "solve":  # what the file lacks, not a signal its header lists
        assert "C2I" in path.read_text() or "Raw," in path.read_text()
        assert "needs epoch records after its header, a GnssLogger log Raw rows" in out.stderr


# matplotlib made unimportable (a None entry in sys.modules makes `import matplotlib` raise
# ImportError), then the command run as `python -m service` runs it
WITHOUT_MATPLOTLIB = (
    "import runpy, sys; sys.modules['matplotlib'] = None; "
    "sys.argv = ['bdsfix', *sys.argv[1:]]; runpy.run_module('service', run_name='__main__')"
)


@pytest.mark.parametrize(
    "args",
    [
        ("ttff", HKSC_OBS, HKSC_NAV, "--trials", "2", "--plot", "PNG"),
        (
            "coverage",
            "--days",
            "1",
            "--step-s",
            "3600",
            "--grid-deg",
            "30",
            "--json",
            "JSON",
            "--plot",
            "PNG",
            "--no-progress",
        ),
    ],
    ids=["ttff", "coverage"],
)
def test_plot_without_matplotlib_refuses_before_computing(args, tmp_path):
    """``--plot`` without matplotlib is exit 2 with the install hint, before any work: no
    result on stdout, no JSON written, no PNG."""
    png, js = tmp_path / "out.png", tmp_path / "out.json"
    argv = [str(png) if a == "PNG" else str(js) if a == "JSON" else a for a in args]
    out = subprocess.run(
        [sys.executable, "-c", WITHOUT_MATPLOTLIB, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 2, out.stderr[-500:]
    assert out.stderr.splitlines() == [
        f"bdsfix {args[0]}: error: --plot needs matplotlib: pip install '.[plot]' in the "
        "bdsfix checkout"
    ]
    assert out.stdout == "" and not js.exists() and not png.exists()
