"""An emulated restart on the HKSC station file with BeiDou, GPS and Galileo
(``replay --restart-at 20 --systems C,G,E``): each system becomes full on its own message.

The restart falls at GPST 358574.0 s (14 s into a 30 s Galileo sub-frame, 2 s into a 6 s
GPS subframe); with bit/page sync 0.1-0.5 s later and ~0.07 s of flight, worked by hand from
the ICDs and the I/NAV schedule read off the PolyU capture: GPS knows its time 1.2 s after the
subframe starting at 358578 (IS-GPS-200 20.3.3.2), at the 1 Hz epoch 358580; Galileo at the
end of the E1-B page of word type 0 starting at GST 17 s of the sub-frame (OS SIS ICD 4.3.5),
19.07 s, at the epoch 358580 too; BeiDou D1 on BDT's 6 s boundaries (2 s off GPST's), D2 on
0.6 s ones. Every integer the fast fixes recovered for a fractional row is confirmed when its
satellite's time arrives.
"""

from __future__ import annotations

import json

from service.commands.cli import main
from tests.support.paths import DATA

OBS = DATA / "hksc-2021" / "hksc1610.obs"
NAV = DATA / "hksc-2021" / "hksc1610.nav"


def test_each_system_becomes_full_on_its_own_message_after_a_restart(tmp_path, capsys):
    out = tmp_path / "out.jsonl"
    argv = ["replay", "--max-speed", "--restart-at", "20", "--systems", "C,G,E"]
    assert main([*argv, "--nav", str(NAV), "--jsonl-out", str(out), str(OBS)]) == 0
    summary = capsys.readouterr().err
    assert "failures 0" in summary and "integrity checks 0," not in summary, summary
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    full = [
        r for r in recs if r["class"] == "TRACK" and r["event"] == "full" and r["since_start_s"] > 0
    ]
    first = {}
    for r in full:
        first.setdefault(r["prn"][0], set()).add((r["nav_type"], r["gpst_tow_s"]))
    assert first["G"] == {("LNAV", 358580.0)}
    assert first["E"] == {("INAV", 358580.0)}
    assert {nav for nav, _ in first["C"]} == {"D1", "D2"}
