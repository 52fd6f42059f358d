"""gpsd reads the NMEA of the Perth phone replay (the golden ``android-perth.nmea``, the
replay's own output, pinned by test_replay_golden) and reports 3-D fixes at our
positions. The Beijing log has no nav file in the data: its replay is refused (exit 3), so
there is no NMEA of it to read."""

from __future__ import annotations

import math

import pytest

from service.output.sinks.nmea_tcp import NmeaTcpServer
from tests.output.test_publish import wait_until
from tests.support.gpsd import gpsd_watching
from tests.support.paths import GOLDEN


def _epochs() -> list[bytes]:
    """The golden's sentences grouped by epoch (each starts with its RMC), CR LF ended."""
    epochs: list[bytes] = []
    for line in (GOLDEN / "android-perth.nmea").read_bytes().splitlines(keepends=True):
        if line.startswith(b"#"):
            continue
        if line[3:6] == b"RMC" or not epochs:
            epochs.append(b"")
        epochs[-1] += line.rstrip(b"\r\n") + b"\r\n"  # the golden file keeps LF only
    return epochs


def _gga_positions(epochs: list[bytes]) -> list[tuple[float, float]]:
    out = []
    for epoch in epochs:
        for line in epoch.split(b"\r\n"):
            f = line.decode().split(",")
            if f[0].endswith("GGA") and f[6] != "0":
                lat = (int(f[2][:2]) + float(f[2][2:]) / 60) * (-1 if f[3] == "S" else 1)
                lon = (int(f[4][:3]) + float(f[4][3:]) / 60) * (-1 if f[5] == "W" else 1)
                out.append((lat, lon))
    return out


@pytest.mark.needs("gpsd")
def test_gpsd_reports_mode_3_at_the_perth_replays_positions():
    epochs = _epochs()
    ours = _gga_positions(epochs)
    # all 445 epochs fix with every system (the replay's default: coarse-time fixes from the
    # first epoch, the phone's time uncertainty as the prior; 418 with BeiDou alone)
    assert len(epochs) == 445 and len(ours) == 445
    server = NmeaTcpServer("127.0.0.1", 0)
    tpv: list[dict] = []
    try:
        with gpsd_watching(f"tcp://127.0.0.1:{server.address[1]}") as gpsd:
            wait_until(lambda: server.n_clients == 1, "gpsd to connect to our NMEA server")
            for epoch in epochs:
                server.write_nmea(epoch)
                tpv += [
                    m for m in gpsd.messages(0.01) if m.get("class") == "TPV" and m.get("mode") == 3
                ]
            for _ in range(100):  # what gpsd still has to say
                got = gpsd.messages(0.1)
                tpv += [m for m in got if m.get("class") == "TPV" and m.get("mode") == 3]
                if not got:
                    break
    finally:
        server.close()
    assert len(tpv) >= 100, len(tpv)
    for t in tpv:  # each at one of our positions (NMEA keeps 1e-7 arc minutes)
        err = min(math.hypot(t["lat"] - a, t["lon"] - b) for a, b in ours)
        assert err < 1e-6, t
    assert all(-32.5 < t["lat"] < -31.5 and 115.5 < t["lon"] < 116.5 for t in tpv)
