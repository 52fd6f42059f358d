"""`bdsfix simulate` writes a UBX capture that the replay decodes into fast then SPP fixes."""

import json

import pytest

from service.commands.cli import main
from tests.support.paths import DATA

NAV = DATA / "hksc-2021/hksc1610.nav"


@pytest.mark.parametrize("rule", ["sow", "subframe"])
def test_simulated_capture_replays_fast_then_spp(tmp_path, rule):
    """prMes valid by the SOW-decode rule (GEO 0.12 s, IGSO/MEO 1.2 s into the first
    subframe after bit sync), or by the old rule at the end of that subframe (0.6 s, 6 s)."""
    ubx, out = tmp_path / "sim.ubx", tmp_path / "fixes.jsonl"
    assert (
        main(
            [
                "simulate",
                "--nav",
                str(NAV),
                "--start",
                "2021-06-10T03:36:00",
                "--lat-deg",
                "22.3",
                "--lon-deg",
                "114.2",
                "--duration-s",
                "15",
                "--out",
                str(ubx),
                "--full-rule",
                rule,
            ]
        )
        == 0
    )
    assert (
        main(["replay", str(ubx), "--nav", str(NAV), "--max-speed", "--jsonl-out", str(out)]) == 0
    )
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX"]
    # the paper's fast fix (four full GEOs); the coarse-time fix may come before it
    first_fast = next(
        f["since_start_s"] for f in fixes if f["mode"] == "fast" and "method" not in f
    )
    first_any = next(f["since_start_s"] for f in fixes if f["mode"] == "fast")
    first_spp = next(f["since_start_s"] for f in fixes if f["mode"] == "spp")
    if rule == "sow":
        assert first_fast <= 1.0 and first_spp >= 1.2
    else:
        assert 0.6 <= first_fast <= 1.5 and first_spp >= 6.0
    assert first_any <= first_fast < first_spp
    sows = [r for r in recs if r["class"] == "TRACK" and r["event"] == "sow"]
    # the nav file carries GPS and Galileo too, and every system is simulated by default:
    # their LNAV subframes and I/NAV pages decode beside BeiDou's D1/D2
    assert {r["nav_type"] for r in sows} == {"D1", "D2", "LNAV", "INAV"}


def test_simulate_rejects_a_bad_start(tmp_path, capsys):
    assert main(["simulate", "--start", "yesterday", "--out", str(tmp_path / "x.ubx")]) == 2
    assert "--start" in capsys.readouterr().err


def test_simulate_with_an_output_publishes_what_a_replay_of_its_stream_publishes(tmp_path):
    """``simulate --output KIND:SPEC`` (the status page is ``http:HOST:PORT``) solves the
    stream it writes in-process: the same FIX and TRACK records as ``bdsfix replay`` of the
    capture it wrote."""
    ubx, here, there = tmp_path / "sim.ubx", tmp_path / "here.jsonl", tmp_path / "there.jsonl"
    args = ["simulate", "--duration-s", "12", "--out", str(ubx), "--output", f"jsonl:{here}"]
    assert main(args) == 0
    assert main(["replay", str(ubx), "--max-speed", "--jsonl-out", str(there)]) == 0
    ours = [json.loads(line) for line in here.read_text().splitlines()]
    theirs = [json.loads(line) for line in there.read_text().splitlines()]
    assert ours == theirs
    fixes = [r for r in ours if r["class"] == "FIX"]
    assert len(fixes) == 120 and {r["mode"] for r in fixes} >= {"fast", "spp"}


def test_simulate_output_is_refused_with_wait_config(capsys):
    assert main(["simulate", "--pty", "--wait-config", "--output", "jsonl:-"]) == 2
    assert "--output is not with --wait-config" in capsys.readouterr().err


def test_simulate_writes_measx_code_phases_of_the_systems_asked(tmp_path):
    """``--measx-systems C,G,E``: RXM-MEASX carries GPS (gnssId 0) and Galileo (gnssId 2)
    satellites beside BeiDou's (3), as a real F9P writes them; by default BeiDou alone. Read
    back with pyubx2 itself, not bdsfix's driver."""
    from pyubx2 import UBXReader

    def measx_gnss(extra: list[str]) -> set[int]:
        ubx = tmp_path / f"sim{len(extra)}.ubx"
        args = ["simulate", "--nav", str(NAV), "--start", "2021-06-10T03:36:00"]
        args += ["--lat-deg", "22.3", "--lon-deg", "114.2", "--duration-s", "2"]
        assert main([*args, "--out", str(ubx), *extra]) == 0
        ids: set[int] = set()
        with ubx.open("rb") as fh:
            for _, msg in UBXReader(fh, protfilter=2):
                if msg is not None and msg.identity == "RXM-MEASX":
                    ids |= {getattr(msg, f"gnssId_{k:02d}") for k in range(1, msg.numSv + 1)}
        return ids

    assert measx_gnss([]) == {3}
    assert measx_gnss(["--measx-systems", "C,G,E"]) == {0, 2, 3}


def test_simulate_refuses_measx_systems_it_does_not_simulate(tmp_path, capsys):
    out = str(tmp_path / "x.ubx")
    assert main(["simulate", "--systems", "C", "--measx-systems", "C,G", "--out", out]) == 2
    assert "--measx-systems" in capsys.readouterr().err
