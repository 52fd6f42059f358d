"""Security: loopback-only defaults, a warning for any other bind, ZeroMQ CURVE with real
sockets (a subscriber holding an allowed key receives FIX; one without CURVE, one with a key
not on the list and one with the wrong server key receive nothing), and no shell=True,
pickle or eval in the code (ruff's bandit rules are on)."""

from __future__ import annotations

import json
import os
import re
import select
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import zmq
import zmq.auth

from service.core.ephemeris import EphemerisStore
from service.core.errors import ConfigError
from service.output.records import fix_record
from service.output.sinks.zmq_pub import ZmqPublisher
from service.sim.keplerian import table1_ephemerides
from tests.support.fixes import hksc_fix
from tests.support.paths import DATA, ROOT

BDSFIX = [sys.executable, "-m", "service"]
HANG_S = 60.0  # waits end here only for a hung run


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _certs(tmp: Path) -> dict[str, Path]:
    """Server, an allowed client (its public cert in clients/), an unknown client, and a
    second server whose public key a misconfigured client holds."""
    for d in ("server", "allowed", "stranger", "other_server", "clients"):
        (tmp / d).mkdir()
    out = {}
    for name in ("server", "allowed", "stranger", "other_server"):
        public, secret = zmq.auth.create_certificates(str(tmp / name), name)
        out[name] = Path(public)
        out[name + "_secret"] = Path(secret)
    (tmp / "clients" / "allowed.key").write_bytes(out["allowed"].read_bytes())
    out["clients"] = tmp / "clients"
    return out


def _sub(ctx: zmq.Context, endpoint: str, server: Path | None, client: Path | None) -> zmq.Socket:
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"FIX")
    if server is not None:
        sock.curve_serverkey = zmq.auth.load_certificate(str(server))[0]
        if client is not None:
            pub, sec = zmq.auth.load_certificate(str(client))
        else:
            pub, sec = zmq.curve_keypair()
        sock.curve_publickey, sock.curve_secretkey = pub, sec
    sock.connect(endpoint)
    return sock


def test_curve_lets_in_only_the_allowed_key(tmp_path):
    c = _certs(tmp_path)
    pub = ZmqPublisher(
        "tcp://127.0.0.1:*",
        curve_secret_key_file=str(c["server_secret"]),
        curve_clients_dir=str(c["clients"]),
    )
    ctx = zmq.Context()
    subs = {
        "allowed": _sub(ctx, pub.endpoint, c["server"], c["allowed_secret"]),
        "no_curve": _sub(ctx, pub.endpoint, None, None),
        "stranger": _sub(ctx, pub.endpoint, c["server"], c["stranger_secret"]),
        "wrong_server_key": _sub(ctx, pub.endpoint, c["other_server"], c["allowed_secret"]),
    }
    got = dict.fromkeys(subs, 0)
    rec = fix_record(hksc_fix(), 1.0)
    try:
        # The refused keep listening for 3 s at least, and until the allowed one has 20
        # messages (a window for a wrong delivery to show; no speed is judged: only a hung
        # run ends at HANG_S).
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline or got["allowed"] < 20:
            assert time.monotonic() < deadline + HANG_S, got
            pub.send("FIX", rec)
            time.sleep(0.005)
            for name, s in subs.items():
                while s.poll(0):
                    topic, body = s.recv_multipart()
                    assert topic == b"FIX" and json.loads(body) == json.loads(json.dumps(rec))
                    got[name] += 1
    finally:
        for s in subs.values():
            s.close(0)
        ctx.term()
        pub.close()
    assert got["allowed"] >= 20
    assert got["no_curve"] == got["stranger"] == got["wrong_server_key"] == 0, got


def test_curve_bad_secret_file_is_a_config_error(tmp_path):
    c = _certs(tmp_path)
    for bad in (tmp_path / "missing.key_secret", c["server"]):  # absent; public only
        try:
            ZmqPublisher("tcp://127.0.0.1:*", curve_secret_key_file=str(bad))
        except ConfigError as exc:
            assert "CURVE" in str(exc)
        else:
            raise AssertionError(f"{bad} accepted")


def test_curve_clients_without_a_server_key_is_refused_not_published_in_the_clear(tmp_path):
    """Issue 23: ``--zmq-curve-clients DIR`` without ``--zmq-curve-secret-key`` published in
    the clear (a plain subscriber got 108 messages): now exit 2, one line, nothing bound."""
    c = _certs(tmp_path)
    port = _free_port()
    proc = subprocess.run(
        [
            *BDSFIX,
            "run",
            "--source",
            str(DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"),
            "--state-dir",
            str(tmp_path / "state"),
            "--nmea-tcp",
            "",
            "--zmq",
            f"tcp://127.0.0.1:{port}",
            "--zmq-curve-clients",
            str(c["clients"]),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "without a server secret key" in lines[0], lines
    with pytest.raises(ConfigError, match="publish in the clear"):
        ZmqPublisher("tcp://127.0.0.1:*", curve_clients_dir=str(c["clients"]))


@pytest.mark.parametrize(
    "bad",
    [
        b"garbage, not a certificate\n",  # no public-key line: pyzmq raises
        b"public-key\n",  # no '=': pyzmq raises IndexError
        b'public-key = "too-short"\n',  # read, but no CURVE key
        b"\x00\xff" * 100,
    ],
    ids=["no-key", "no-equals", "short-key", "binary"],
)
def test_one_malformed_client_certificate_is_refused_by_name(tmp_path, bad, caplog):
    """Issue 23: one malformed ``*.key`` in the clients directory made pyzmq's loader fail
    and allow no client at all, silently. Now the configuration is refused naming the
    file; a good directory says how many clients it allows."""
    import logging

    c = _certs(tmp_path)
    (c["clients"] / "zz-broken.key").write_bytes(bad)
    with pytest.raises(ConfigError, match=r"zz-broken\.key") as err:
        ZmqPublisher(
            "tcp://127.0.0.1:*",
            curve_secret_key_file=str(c["server_secret"]),
            curve_clients_dir=str(c["clients"]),
        )
    assert len(str(err.value).splitlines()) == 1
    (c["clients"] / "zz-broken.key").unlink()
    (c["clients"] / "stranger.key").write_bytes(c["stranger"].read_bytes())
    caplog.set_level(logging.INFO)
    pub = ZmqPublisher(
        "tcp://127.0.0.1:*",
        curve_secret_key_file=str(c["server_secret"]),
        curve_clients_dir=str(c["clients"]),
    )
    pub.close()
    assert any("2 clients allowed" in r.getMessage() for r in caplog.records)


def test_daemon_and_bdsfix_sub_with_curve_and_a_warned_public_bind(tmp_path):
    """`bdsfix run` reading a simulated receiver on a pty, CURVE on, NMEA on 0.0.0.0:
    `bdsfix sub` with the allowed key prints FIX records, a keyless one prints nothing."""
    c = _certs(tmp_path)
    state = tmp_path / "state"
    state.mkdir()
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")
    sim = subprocess.Popen(
        [*BDSFIX, "simulate", "--pty", "--duration-s", "40", "--rate-hz", "10"],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
    )
    assert sim.stderr is not None
    ready, _, _ = select.select([sim.stderr], [], [], HANG_S)
    assert ready, "simulate --pty printed no device"
    device = sim.stderr.readline().decode().strip()
    assert device.startswith("/dev/")
    zport, nport = _free_port(), _free_port()
    endpoint = f"tcp://127.0.0.1:{zport}"
    daemon = subprocess.Popen(
        [
            *BDSFIX,
            "run",
            "--source",
            device,
            "--state-dir",
            str(state),
            "--zmq",
            endpoint,
            "--zmq-curve-secret-key",
            str(c["server_secret"]),
            "--zmq-curve-clients",
            str(c["clients"]),
            "--nmea-tcp",
            f"0.0.0.0:{nport}",
            "--log-level",
            "warning",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
    )
    sub_args = [*BDSFIX, "sub", endpoint, "--topic", "FIX", "--count", "5", "--timeout-s"]
    server = ["--curve-server-key", str(c["server"])]
    try:
        good = subprocess.run(  # exits after 5 FIX; 60 s without one is a hang
            [*sub_args, str(HANG_S), *server, "--curve-key", str(c["allowed_secret"])],
            cwd=ROOT,
            capture_output=True,
            timeout=2 * HANG_S,
        )
        # the daemon is publishing now: these two listen 4 s each, side by side
        others = [
            subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            for cmd in (
                [*sub_args, "4"],
                [*sub_args, "4", *server, "--curve-key", str(c["stranger_secret"])],
            )
        ]
        (k_out, _), (s_out, _) = (p.communicate(timeout=2 * HANG_S) for p in others)
        assert [p.returncode for p in others] == [0, 0]
    finally:
        daemon.terminate()
        _, err = daemon.communicate(timeout=HANG_S)
        sim.kill()
        sim.communicate()
    assert good.returncode == 0, good.stderr
    lines = good.stdout.decode().splitlines()
    assert len(lines) == 5 and all(line.startswith("FIX {") for line in lines), lines
    assert all(json.loads(line[4:])["class"] == "FIX" for line in lines)
    assert k_out == b"" and s_out == b""  # no CURVE; a key not on the list
    text = err.decode()
    assert re.search(rf"WARNING .*0\.0\.0\.0:{nport}.*not loopback", text), text
    assert "Traceback" not in text


def test_outputs_are_loopback_by_default_in_code_and_example_config():
    from service.daemon.config import DaemonConfig

    example = tomllib.loads((ROOT / "systemd" / "bdsfix.toml").read_text())
    for cfg in (DaemonConfig(), example):
        get = cfg.get if isinstance(cfg, dict) else lambda k, c=cfg: getattr(c, k)
        assert get("nmea_tcp").startswith("127.0.0.1:")
        assert get("zmq").startswith("tcp://127.0.0.1:")


def test_ruff_security_rules_are_on_and_no_shell_pickle_eval():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "S" in pyproject["tool"]["ruff"]["lint"]["select"]
    pattern = re.compile(r"shell\s*=\s*True|\bimport pickle\b|\bpickle\.|\beval\(|\bexec\(")
    hits = []
    for d in ("service", "drivers", "bench"):
        for path in (ROOT / d).rglob("*.py"):
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if pattern.search(line):
                    hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not hits, hits
    env = {**os.environ}
    res = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--select", "S", "service", "drivers"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
    )
    assert res.returncode == 0, res.stdout + res.stderr


def test_curve_keys_from_toml_and_flags(tmp_path):
    import argparse

    from service.daemon.config import add_config_flags, load_config, overrides_from_args

    p = tmp_path / "bdsfix.toml"
    p.write_text('zmq_curve_secret_key = "/etc/k/server.key_secret"\nzmq_curve_clients = "/c"\n')
    cfg = load_config(p)
    assert (cfg.zmq_curve_secret_key, cfg.zmq_curve_clients) == ("/etc/k/server.key_secret", "/c")
    parser = argparse.ArgumentParser()
    add_config_flags(parser)
    args = parser.parse_args(["--zmq-curve-clients", "/d"])
    assert load_config(p, overrides_from_args(args)).zmq_curve_clients == "/d"
    p.write_text("zmq_curve_clients = 3\n")
    with pytest.raises(ConfigError, match="zmq_curve_clients"):
        load_config(p)
