"""TOML configuration and its flags: every key a flag, clear one-line errors."""

import argparse
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from service.core.errors import ConfigError
from service.core.receiver_setup import ReceiverSetup
from service.daemon.config import (
    DaemonConfig,
    add_config_flags,
    load_config,
    overrides_from_args,
    toml_shape_problem,
)
from service.engine.solver import SolverConfig
from tests.support.paths import ROOT

HANG_S = 60.0  # only a hung run ends here


def _write(tmp_path, text):
    p = tmp_path / "bdsfix.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_defaults_bind_loopback_only():
    cfg = load_config(None)
    assert cfg.nmea_tcp.startswith("127.0.0.1:") and cfg.zmq.startswith("tcp://127.0.0.1:")


def test_file_values_and_flag_overrides(tmp_path):
    p = _write(
        tmp_path,
        'source = "/dev/ttyACM0"\nbaud = 38400\nnav = ["a.nav", "b.nav"]\n'
        'elmask_deg = 5\ntropo = "off"\n',
    )
    parser = argparse.ArgumentParser()
    add_config_flags(parser)
    args = parser.parse_args(["--baud", "9600", "--talker", "GB"])
    cfg = load_config(p, overrides_from_args(args))
    assert cfg == DaemonConfig(
        source="/dev/ttyACM0",
        baud=9600,
        nav=("a.nav", "b.nav"),
        talker="GB",
        solver=SolverConfig(elmask_deg=5.0, tropo="off"),
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sauce = 1\n", "unknown key 'sauce'"),
        ('baud = "fast"\n', "key 'baud' must be int"),
        ("tropo = true\n", "key 'tropo' must be str"),
        ('tropo = "on"\n', "key 'tropo' must be one of saastamoinen, off"),
        ("p_fa = 0.7\n", "key 'p_fa' must be in [0, 0.5]"),
        ("max_exclusions = -1\n", "key 'max_exclusions' must be in [0, 10]"),
        ('talker = "XX"\n', "key 'talker' must be one of"),
        ("baud = \n", "not valid TOML"),
        ("nav = [1]\n", "key 'nav' must be a list of strings"),
        ('configure = "yes"\n', "key 'configure' must be bool"),
        ('configure_model = "m9"\n', "key 'configure_model' must be one of m8, f9, x20"),
        ("configure_rate_hz = 0\n", "key 'configure_rate_hz' must be in (0, 40]"),
        ('model = "f9"\n', "unknown key 'model'"),
    ],
)
def test_bad_config_names_file_and_key(tmp_path, text, message):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert message in str(exc.value) and str(p) in str(exc.value)
    assert "\n" not in str(exc.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_receiver_setup_keys_and_flags(tmp_path):
    """configure = true and the configure_* keys (the settings of `bdsfix configure`, with
    a prefix), from the file and as flags."""
    p = _write(tmp_path, 'configure = true\nconfigure_model = "m8"\nconfigure_rate_hz = 5\n')
    parser = argparse.ArgumentParser()
    add_config_flags(parser)
    args = parser.parse_args(["--configure-port", "usb", "--configure-timeout-s", "0.5"])
    cfg = load_config(p, overrides_from_args(args))
    assert cfg.configure is True
    assert cfg.setup == ReceiverSetup(model="m8", rate_hz=5.0, port="usb", timeout_s=0.5)
    assert load_config(None).configure is False


# --- issue 23: files that exhaust memory, a typo, the [solver] table -----------------------


def _limited_run(*args: str) -> subprocess.CompletedProcess[str]:
    """``bdsfix run`` with its address space capped at 1 GiB, so a reader that does not
    bound what it reads fails here (MemoryError) instead of taking the machine's memory."""

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))

    return subprocess.run(
        [sys.executable, "-m", "service", "run", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
        preexec_fn=cap,
    )


@pytest.mark.parametrize(
    ("name", "text", "words"),
    [
        ("dev-zero", None, "config larger than 1 MiB"),
        ("dotted", ".".join(["a"] * 100_000) + " = 1\n", "dotted key of more than 8 parts"),
        ("arrays", "x = " + "[" * 100_000 + "]" * 100_000 + "\n", "nesting deeper than 8"),
        ("tables", "x = " + "{a=" * 5_000 + "1" + "}" * 5_000 + "\n", "nesting deeper than 8"),
        ("headers", "[" + ".".join(["t"] * 50_000) + "]\n", "dotted key of more than 8 parts"),
    ],
)
def test_config_files_that_would_exhaust_memory_are_refused_in_one_line(
    tmp_path, name, text, words
):
    """Issue 23: ``--config /dev/zero`` read until MemoryError, one key of 100,000 dotted
    parts took more than 11.8 GB (tomllib is quadratic there), deep nesting ended in
    "internal error: RecursionError". Now: exit 2, one line naming the file and why."""
    path = Path("/dev/zero") if text is None else tmp_path / f"{name}.toml"
    if text is not None:
        path.write_text(text)
    proc = _limited_run("--config", str(path), "--source", str(tmp_path / "none"))
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and words in lines[0], lines
    assert len(lines[0]) < 300


@pytest.mark.parametrize(
    ("text", "start", "length"),
    [
        ('baud = "' + "9" * 500_000 + '"\n', "key 'baud' must be int, got str '999", 500_002),
        ("elmask_deg = [" + "1," * 50_000 + "]\n", "key 'elmask_deg' must be float", 150_000),
        ("baud = " + "9" * 400 + "\n", "key 'baud' must be in [1, 4e+06], got 999", 400),
    ],
)
def test_a_bad_value_is_echoed_in_a_few_hundred_characters_at_most(tmp_path, text, start, length):
    """Issue 23: the whole value was echoed (megabytes on the terminal and in the journal)."""
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert start in msg and len(msg) < 400
    assert f"({length} characters)" in msg


def test_the_shape_scan_passes_every_valid_config_whatever_its_strings_hold(tmp_path):
    """Dots and brackets in strings and comments, floats, dates: nothing of it is a dotted
    key or nesting; the example config loads as it is."""
    text = (
        "# a.b.c.d.e.f.g.h.i.j [[[[[[[[[[ {{{{{{{{{\n"
        "nav = [\"a.b.c.d.e.f.g.h.i.j.k.nav\", '[[[[[[[[[[[[.{{{{{{{{{']\n"
        'source = """\n[[[[[[[[[[ a.b.c.d.e.f.g.h.i.j\n"""\n'
        "elmask_deg = 12.5  # 1.2.3.4.5.6.7.8.9.10\n"
        "p_fa = 1.5e-3\n"
    )
    p = _write(tmp_path, text)
    assert toml_shape_problem(text) is None
    cfg = load_config(p)
    assert cfg.nav == ("a.b.c.d.e.f.g.h.i.j.k.nav", "[[[[[[[[[[[[.{{{{{{{{{")
    assert cfg.solver.elmask_deg == 12.5
    load_config(ROOT / "systemd" / "bdsfix.toml")


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("elmask = 5\n", "unknown key 'elmask' (did you mean 'elmask_deg'?)"),
        ('nmea_tpc = ""\n', "unknown key 'nmea_tpc' (did you mean 'nmea_tcp'?)"),
        ("ntrip_max_age = 60.0\n", "(did you mean 'ntrip_max_age_s'?)"),
        ("zzzz = 1\n", "unknown key 'zzzz'"),
        ("[solver]\nelmask_deg = 5\n", "[solver] is a table, and bdsfix.toml has none"),
        ("solver.elmask_deg = 5\n", "[solver] is a table"),
    ],
)
def test_an_unknown_key_names_the_nearest_known_one(tmp_path, text, words):
    """Issue 23: a misspelt key said only "unknown key"; the README spoke of a ``[solver]``
    table the reader refused as an unknown key (the docs now say the keys are flat)."""
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert words in str(exc.value)
    assert "did you mean" not in str(exc.value) or "zzzz" not in text


def test_the_docs_speak_of_no_solver_table():
    for doc in ("README.md", "docs/architecture.md"):
        text = (ROOT / doc).read_text()
        assert "`[solver]` keys" not in text and "[solver] keys" not in text, doc
