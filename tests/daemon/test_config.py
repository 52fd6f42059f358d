"""TOML configuration and its flags: every key a flag, clear one-line errors."""

import argparse

import pytest

from service.core.errors import ConfigError
from service.core.receiver_setup import ReceiverSetup
from service.daemon.config import DaemonConfig, add_config_flags, load_config, overrides_from_args
from service.engine.solver import SolverConfig


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
