"""``bdsfix replay`` of the Leuven Septentrio SBF capture against the receiver's own fix.

The reference is each epoch's PVTGeodetic block as pysbf2 parses it (the mosaic's own
position, SBAS-aided, metre level); the capture's nav blocks are the only ephemerides.
"""

from __future__ import annotations

import json
import os

import numpy as np
from pysbf2 import SBFReader

from service.commands.cli import main
from service.core.geometry import geodetic_to_ecef
from tests.support.paths import DATA

LOG = DATA / "leuven-septentrio-sbf-2025/log_0000.sbf"


def test_every_epoch_fixes_within_10_m_of_the_receivers_pvtgeodetic(tmp_path, capsys):
    ref = {}
    with open(LOG, "rb") as fh:
        for raw, msg in SBFReader(fh):
            if msg.identity == "PVTGeodetic":
                tow = int.from_bytes(raw[8:12], "little") / 1000
                ref[tow] = geodetic_to_ecef(msg.Latitude, msg.Longitude, msg.Height)
    out = tmp_path / "fix.jsonl"
    args = ["replay", str(LOG), "--max-speed", "--jsonl-out", str(out), "--nmea-out", os.devnull]
    assert main(args) == 0
    fixes = [r for r in map(json.loads, out.read_text().splitlines()) if r["class"] == "FIX"]
    assert len(fixes) == len(ref) == 12
    for fix in fixes:
        assert fix["mode"] == "spp", fix.get("reason")
        err = np.linalg.norm(np.array(fix["x_ecef_m"]) - ref[fix["gpst_tow_s"]])
        assert err < 10.0, (fix["gpst_tow_s"], err)
    assert "spp 12, none 0" in capsys.readouterr().err
