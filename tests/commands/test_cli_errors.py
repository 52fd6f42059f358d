"""Bad configuration and arguments through the real ``bdsfix`` console script: each gives
exactly one line on stderr (default verbosity), the documented exit code (service/core/errors.py,
README "Exit codes") and never a traceback. Ports in use are held by real sockets."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import zmq

from tests.support.captures import ubx_poll_capture
from tests.support.paths import DATA

BDSFIX = str(Path(sys.executable).parent / "bdsfix")
NAV = DATA / "hksc-2021" / "hksc1610.nav"
# The documented table, written out here rather than imported from the code under test.
USAGE, INPUT, BIND = 2, 3, 4
QUIET = ["--nmea-tcp", "", "--zmq", "", "--state-dir", "state"]


def _bdsfix(cwd: Path, *argv: str) -> tuple[int, list[str], str]:
    proc = subprocess.run(
        [BDSFIX, *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    return proc.returncode, [ln for ln in proc.stderr.splitlines() if ln.strip()], proc.stderr


def _one_clear_line(cwd: Path, code: int, argv: list[str], *needles: str) -> str:
    rc, lines, err = _bdsfix(cwd, *argv)
    assert "Traceback" not in err, err
    assert rc == code, (rc, err)
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith("bdsfix") and "error:" in line, line
    for needle in needles:
        assert needle in line, (needle, line)
    return line


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    """A readable (tiny) capture file, so that checks after the source are reached: one UBX
    NAV-PVT poll frame (empty payload)."""
    return ubx_poll_capture(tmp_path / "capture.ubx")


def _toml(tmp_path: Path, text: str) -> str:
    p = tmp_path / "bdsfix.toml"
    p.write_text(text, encoding="utf-8")
    return str(p)


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        ('sauce = "x"\n', ["unknown key 'sauce'"]),
        ('baud = "fast"\n', ["'baud' must be int"]),
        ("tropo = 1\n", ["'tropo' must be str"]),
        ("status_interval_s = -1.0\n", ["'status_interval_s'", "-1.0"]),
        ("elmask_deg = nan\n", ["'elmask_deg'", "nan"]),
        ("baud = \n", ["not valid TOML"]),
    ],
)
def test_bad_config_file_exits_2(tmp_path, text, needles):
    path = _toml(tmp_path, text)
    _one_clear_line(tmp_path, USAGE, ["run", "--config", path], path, *needles)


def test_missing_and_unreadable_config_file_exit_2(tmp_path):
    _one_clear_line(tmp_path, USAGE, ["run", "--config", "nope.toml"], "nope.toml", "not found")
    (tmp_path / "conf.d").mkdir()  # unreadable as a file, even for root
    _one_clear_line(tmp_path, USAGE, ["run", "--config", "conf.d"], "conf.d", "cannot read")
    if os.geteuid() != 0:  # root reads a mode-000 file; the directory case stands for it
        path = _toml(tmp_path, 'source = "/dev/ttyACM0"\n')
        os.chmod(path, 0)
        _one_clear_line(tmp_path, USAGE, ["run", "--config", path], "cannot read")


@pytest.mark.parametrize(
    ("argv", "needles"),
    [
        (["run", "--baud", "abc"], ["--baud", "invalid int value"]),
        (["run", "--baud", "0", "--source", "x"], ["'baud'", "got 0"]),
        (["run", "--elmask-deg", "nan", "--source", "x"], ["'elmask_deg'"]),
        (["run", "--max-eph-age-s", "-5", "--source", "x"], ["'max_eph_age_s'"]),
        (["run", "--talker", "XX"], ["--talker", "invalid choice"]),
        (["run", "--tropo", "maybe"], ["--tropo"]),
        (["run", "--sauce", "1"], ["unrecognized arguments: --sauce"]),
        (["run", *QUIET], ["no receiver source"]),
        (["run", "--source", "capture.ubx", "--nmea-tcp", "nope", "--zmq", ""], ["HOST:PORT"]),
        (["run", "--source", "capture.ubx", "--nmea-tcp", "", "--zmq", "nope"], ["ZeroMQ nope"]),
        (["run", "--source", "capture.ubx", *QUIET, "--output", "pigeon:x"], ["'pigeon'"]),
        (["replay", "--output", "jsonl"], ["KIND:SPEC"]),
        (["frobnicate"], ["invalid choice"]),
        (["solve", "--mode", "slow", "a.obs", "b.nav"], ["--mode"]),
        (["replay", "--speed", "fast"], ["--speed"]),
        (["replay", "--speed", "-1"], ["--speed must be a positive number"]),
        (["simulate", "--rate-hz", "0", "--out", "x.ubx"], ["--rate-hz"]),
        (["ttff", "--simulate", "--full-rule", "end"], ["--full-rule", "invalid choice"]),
        (["sub", "not-an-endpoint", "--count", "1"], ["not-an-endpoint"]),
    ],
)
def test_bad_arguments_exit_2(tmp_path, capture, argv, needles):
    _one_clear_line(tmp_path, USAGE, argv, *needles)


def test_missing_device_exits_3(tmp_path):
    """A serial device that is not there at start is an error; one that vanishes later is
    waited for (tests/system/test_serial_faults.py)."""
    dev = str(tmp_path / "ttyNOPE")
    for spec in ("/dev/ttyBDSFIX-NOPE", f"serial:{dev}:9600"):
        _one_clear_line(tmp_path, INPUT, ["run", "--source", spec, *QUIET], "No such file")
    dangling = tmp_path / "ttyGONE"
    dangling.symlink_to(tmp_path / "missing-pty")
    _one_clear_line(tmp_path, INPUT, ["run", "--source", str(dangling), *QUIET], "ttyGONE")


def test_missing_or_unreadable_capture_exits_3(tmp_path):
    _one_clear_line(tmp_path, INPUT, ["run", "--source", "gone.ubx", *QUIET], "gone.ubx")
    (tmp_path / "adir").mkdir()
    _one_clear_line(tmp_path, INPUT, ["run", "--source", "adir", *QUIET], "adir")
    _one_clear_line(tmp_path, INPUT, ["replay", "gone.ubx", "--max-speed"], "gone.ubx")


def test_unreadable_or_malformed_nav_file_exits_3(tmp_path, capture):
    (tmp_path / "nav.d").mkdir()
    (tmp_path / "junk.nav").write_text("this is not RINEX\n")
    for nav, needle in [
        ("missing.nav", "cannot read"),
        ("nav.d", "cannot read"),
        ("junk.nav", "not a RINEX file"),
    ]:
        argv = ["run", "--source", str(capture), "--nav", nav, *QUIET]
        _one_clear_line(tmp_path, INPUT, argv, nav, needle)
    _one_clear_line(tmp_path, INPUT, ["solve", "missing.obs", "missing.nav"], "missing")


def test_unwritable_output_or_state_dir_exits_3(tmp_path, capture):
    argv = ["run", "--source", str(capture), *QUIET, "--jsonl-out", "no/such/dir/fixes.jsonl"]
    _one_clear_line(tmp_path, INPUT, argv, "fixes.jsonl")
    argv = ["run", "--source", str(capture), *QUIET, "--output", "jsonl:no/such/dir/x.jsonl"]
    _one_clear_line(tmp_path, INPUT, argv, "x.jsonl")
    argv = ["run", "--source", str(capture), *QUIET, "--state-dir", str(capture)]
    _one_clear_line(tmp_path, INPUT, argv, "state directory", "not a directory")
    argv = ["simulate", "--duration-s", "1", "--out", "no/such/dir/x.ubx"]
    _one_clear_line(tmp_path, INPUT, argv, "x.ubx")


def test_nmea_port_in_use_exits_4(tmp_path, capture):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        argv = ["run", "--source", str(capture), *QUIET, "--nmea-tcp", f"127.0.0.1:{port}"]
        _one_clear_line(tmp_path, BIND, argv, f"127.0.0.1:{port}", "in use")


def test_port_in_use_with_a_live_serial_source_is_still_one_line(tmp_path):
    """The device opens fine (a pty), then the NMEA port is taken: one line, exit 4."""
    master, slave = os.openpty()
    try:
        with socket.socket() as held:
            held.bind(("127.0.0.1", 0))
            held.listen()
            port = held.getsockname()[1]
            argv = ["run", "--source", os.ttyname(slave), *QUIET, "--nmea-tcp", f":{port}"]
            _one_clear_line(tmp_path, BIND, argv, f"127.0.0.1:{port}", "in use")
    finally:
        os.close(master)
        os.close(slave)


def test_zmq_port_in_use_exits_4(tmp_path, capture):
    ctx = zmq.Context.instance()
    held = ctx.socket(zmq.PUB)
    try:
        port = held.bind_to_random_port("tcp://127.0.0.1")
        endpoint = f"tcp://127.0.0.1:{port}"
        argv = ["run", "--source", str(capture), *QUIET, "--zmq", endpoint]
        _one_clear_line(tmp_path, BIND, argv, endpoint, "in use")
        argv = [
            "replay",
            str(capture),
            "--max-speed",
            "--zmq",
            endpoint,
        ]  # replay binds the same way
        _one_clear_line(tmp_path, BIND, argv, endpoint)
    finally:
        held.close(0)


def test_a_good_start_still_exits_0(tmp_path, capture):
    """The same daemon with a valid (short) capture runs to its end and exits 0."""
    rc, _, err = _bdsfix(tmp_path, "run", "--source", str(capture), *QUIET, "--log-level", "error")
    assert rc == 0 and "Traceback" not in err, err


def test_replay_stops_when_the_reader_of_its_only_output_leaves():
    """`bdsfix replay ... | head -n 2`: the pipe's reader leaves after two lines; the replay
    stops there (exit 0, no traceback, no broken-pipe noise) instead of replaying on."""
    hk = DATA / "hksc-2021"
    rd, wr = os.pipe()
    argv = [BDSFIX, "replay", str(hk / "hksc1610.obs"), "--nav", str(hk / "hksc1610.nav")]
    proc = subprocess.Popen([*argv, "--max-speed"], stdout=wr, stderr=subprocess.PIPE, text=True)
    os.close(wr)
    with os.fdopen(rd) as reader:
        first = [reader.readline() for _ in range(2)]
    _, err = proc.communicate(timeout=120)
    assert first[0].startswith("$GNRMC,") and first[1].startswith(("$GNVTG,", "$GNGGA,"))
    assert proc.returncode == 0, err
    for noise in ("Traceback", "Exception ignored", "Broken pipe"):
        assert noise not in err, err
    # 205 epochs of NMEA (~140 kB) cannot pass a 64 kB pipe nobody reads: it stopped early
    epochs = int(re.search(r"bdsfix replay: (\d+) epochs", err).group(1))
    assert epochs < 205
