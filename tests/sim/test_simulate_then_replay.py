"""``bdsfix simulate --out sim.ubx && bdsfix replay sim.ubx --max-speed`` gives fast fixes
with no other argument: the stream starts with the ephemerides it was made with (RTCM 1042),
as an assisted receiver holds them. The 1042 frames are read back by pyrtcm (an independent
decoder) and the driver, and every published fix is checked against the simulated truth."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from pyrtcm import RTCMReader

from drivers.rtcm import ephemeris_from_1042
from service.core.geometry import geodetic_to_ecef
from service.sim.rtcm import frame_1042
from service.sim.scenario import broadcast_table1
from tests.support.paths import DATA, ROOT

HKSC_NAV = DATA / "hksc-2021" / "hksc1610.nav"


def test_1042_frames_read_back_as_the_ephemerides_they_encode():
    for eph in broadcast_table1():
        msg = RTCMReader.parse(frame_1042(eph))
        assert msg.identity == "1042" and int(msg.DF488) == int(eph.prn[1:])
        back = ephemeris_from_1042(msg)
        assert back.week == eph.week and back.toe_sow_s == eph.toe_sow_s
        assert abs(back.sqrt_a_sqrt_m - eph.sqrt_a_sqrt_m) < 2e-6  # 2^-19 sqrt(m) LSB
        assert abs(back.e - eph.e) < 1e-10  # 2^-33
        for name in ("i0_rad", "omega0_rad", "omega_rad", "m0_rad"):
            assert abs(getattr(back, name) - getattr(eph, name)) < 1e-9, name  # 2^-31 sc


@pytest.mark.parametrize(
    ("extra", "truth"),
    [
        ((), (39.9, 116.4, 50.0)),
        (("--nav", str(HKSC_NAV), "--lat-deg", "22.3", "--lon-deg", "114.2"), (22.3, 114.2, 50.0)),
    ],
    ids=["table1-beijing", "hksc-nav-hong-kong"],
)
def test_a_simulated_capture_replays_to_a_fast_fix_within_1_2_s(tmp_path, extra, truth):
    sim, jsonl = tmp_path / "sim.ubx", tmp_path / "fixes.jsonl"
    run = subprocess.run(
        [sys.executable, "-m", "service", "simulate", "--out", str(sim), *extra],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    replay = ["replay", str(sim), "--max-speed", "--jsonl-out", str(jsonl)]
    run = subprocess.run(
        [sys.executable, "-m", "service", *replay],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    fixes = [r for r in map(json.loads, jsonl.read_text().splitlines()) if r["class"] == "FIX"]
    first_fast = min(r["since_start_s"] for r in fixes if r["mode"] == "fast")
    assert first_fast <= 1.2
    x_true = geodetic_to_ecef(math.radians(truth[0]), math.radians(truth[1]), truth[2])
    errors = [np.linalg.norm(np.subtract(r["x_ecef_m"], x_true)) for r in fixes if "x_ecef_m" in r]
    assert len(errors) > 500 and max(errors) < 30.0
