"""A damaged ephemeris store never stops the daemon: whatever is in the file (truncated,
not JSON, JSON of the wrong shape, wrong field types), it is moved aside to
``ephemeris.json.corrupt-<UTC time>`` with one WARNING line and the daemon starts empty and
exits 0 at the end of its source."""

from __future__ import annotations

import dataclasses
import json
import logging
import subprocess
import sys

import pytest

from service.commands.run import load_store
from service.sim.keplerian import table1_ephemerides
from tests.support.paths import DATA, ROOT

CAPTURE = DATA / "tiny-ubx-rtcm" / "pygpsdata-RXMRAWX.log"


def _good() -> dict:
    """A store as the daemon writes it: two Table 1 sets."""
    ephs = [dataclasses.asdict(e) for e in table1_ephemerides(0.0)[:2]]
    return {"version": 1, "ephemerides": ephs, "iono": None}


def _damaged() -> dict[str, bytes]:
    good = json.dumps(_good()).encode()
    item = _good()["ephemerides"][0]
    shaped = {
        "list": [1, 2],
        "ephemerides a number": {"ephemerides": 5},
        "version 1, ephemerides a number": {"version": 1, "ephemerides": 5},
        "week a string": {"version": 1, "ephemerides": [{**item, "week": "x"}], "iono": None},
        "e a list": {"version": 1, "ephemerides": [{**item, "e": [0.1]}], "iono": None},
        "iono a number": {"version": 1, "ephemerides": [item], "iono": 3},
        "null": None,
    }
    return {
        "truncated": good[: len(good) // 2],
        "empty": b"",
        "binary": bytes(range(256)),
        **{name: json.dumps(doc).encode() for name, doc in shaped.items()},
    }


@pytest.mark.parametrize("name", sorted(_damaged()))
def test_load_store_sets_a_damaged_store_aside_and_starts_empty(tmp_path, caplog, name):
    raw = _damaged()[name]
    (tmp_path / "ephemeris.json").write_bytes(raw)
    with caplog.at_level(logging.INFO):
        store = load_store(tmp_path, 7200.0)
    assert len(store) == 0
    aside = list(tmp_path.glob("ephemeris.json.corrupt-*"))
    assert len(aside) == 1 and aside[0].read_bytes() == raw
    assert not (tmp_path / "ephemeris.json").exists()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    line = warnings[0].getMessage()
    assert warnings[0].levelno == logging.WARNING and "\n" not in line
    assert str(aside[0]) in line and "starting with an empty store" in line


def test_a_good_store_still_warm_starts(tmp_path):
    (tmp_path / "ephemeris.json").write_text(json.dumps(_good()))
    assert len(load_store(tmp_path, 7200.0)) == 2
    assert not list(tmp_path.glob("ephemeris.json.corrupt-*"))


@pytest.mark.parametrize("name", ["list", "truncated", "week a string"])
def test_the_daemon_runs_on_with_a_damaged_store(tmp_path, name):
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    (state / "ephemeris.json").write_bytes(_damaged()[name])
    argv = [sys.executable, "-m", "service", "run", "--source", str(CAPTURE)]
    argv += ["--state-dir", str(state), "--nmea-tcp", "", "--zmq", "", "--log-level", "info"]
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    aside = list(state.glob("ephemeris.json.corrupt-*"))
    assert len(aside) == 1
    lines = [ln for ln in done.stderr.splitlines() if "moved aside" in ln]
    assert len(lines) == 1 and lines[0].startswith("WARNING") and str(aside[0]) in lines[0]
    assert "Traceback" not in done.stderr and "ERROR" not in done.stderr
