"""Replays of real captures against golden JSONL and NMEA (``pytest --regen-golden``).

A change to a golden file must say why in its commit. Numbers compare within the last
printed digit, so a different libm cannot fail the test while any real change does.
"""

from __future__ import annotations

import json
import math

import pytest

from service.commands.cli import main
from tests.support.paths import DATA, GOLDEN

CASES = {
    "polyu-f9p-ubx": [
        "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx",
        "--nav",
        "hk-polyu-f9p-ubx-2024/hksc269h.24f",
    ],
    "ublox-x20p": ["ublox-logs/ublox-x20p.log"],
    "ublox-zed-f9p-sfrbx": ["ublox-logs/ublox-zed-f9p-sfrbx.log"],
    "ublox-zed-f9p-hpg111": ["ublox-logs/ublox-zed-f9p_hpg1.11.log"],
    "ublox-zed-f9r": ["ublox-logs/ublox-zed-f9r.log"],
    "tiny-ntrip": ["tiny-ubx-rtcm/pygpsdata-NTRIP-USCL00CHL0.log"],
    "tiny-rtcm3": ["tiny-ubx-rtcm/pygpsdata-RTCM3.log", "--gps-week", "2200"],
    "tiny-rawx": ["tiny-ubx-rtcm/pygpsdata-RXMRAWX.log"],
    "hksc-rinex": ["hksc-2021/hksc1610.obs", "--nav", "hksc-2021/hksc1610.nav"],
}


def _args(parts):
    out = []
    for p in parts:
        out.append(str(DATA / p) if "/" in p else p)
    return out


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
def test_replay_matches_golden(name, tmp_path, request):
    jsonl, nmea = tmp_path / "out.jsonl", tmp_path / "out.nmea"
    rc = main(
        [
            "replay",
            *_args(CASES[name]),
            "--max-speed",
            "--jsonl-out",
            str(jsonl),
            "--nmea-out",
            str(nmea),
        ]
    )
    assert rc == 0
    g_jsonl, g_nmea = GOLDEN / f"{name}.jsonl", GOLDEN / f"{name}.nmea"
    if request.config.getoption("--regen-golden"):
        GOLDEN.mkdir(exist_ok=True)
        g_jsonl.write_text(jsonl.read_text())
        g_nmea.write_text(nmea.read_text())
        pytest.skip("golden files regenerated")
    got = [json.loads(x) for x in jsonl.read_text().splitlines()]
    want = [json.loads(x) for x in g_jsonl.read_text().splitlines()]
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert _same_json(g, w), (i, g, w)
    got_n, want_n = nmea.read_text().splitlines(), g_nmea.read_text().splitlines()
    assert len(got_n) == len(want_n)
    for g, w in zip(got_n, want_n, strict=True):
        gf, wf = g.split("*")[0].split(","), w.split("*")[0].split(",")
        assert len(gf) == len(wf) and all(_same_field(a, b) for a, b in zip(gf, wf, strict=True)), (
            g,
            w,
        )
