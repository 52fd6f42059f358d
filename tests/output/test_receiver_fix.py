"""The receiver's own fix carried on the FIX records for comparison (an SBF PVTGeodetic, an
Android Fix row): one mechanism, ReceiverFix events through the pipeline to the record."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest

from drivers.gnsslogger import GnssLoggerReader
from service.commands.cli import main
from service.core.ephemeris import EphemerisStore
from service.core.types import MeasurementEpoch, ReceiverFix
from service.engine.pipeline import Pipeline
from service.output.records import SCHEMAS, fix_record
from tests.drivers.test_sbf import _receiver_fixes
from tests.support.paths import DATA

LEUVEN = DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf"
BEIJING = DATA / "android-beijing-mi8-2022" / "gnss_log_2022_09_28_22_01_27.txt"


def test_sbf_pvtgeodetic_rides_on_every_fix_record(tmp_path, capsys):
    """Leuven: each of the 12 FIX records carries the PVTGeodetic of its second (the first,
    held until the nav blocks came, of the same second: age 0) or of the second before
    (age 1 s: PVTGeodetic follows its MeasEpoch), and ``dist_m`` is the distance from our
    fix to that position computed here from pysbf2's values (measured 5.9-6.6 m)."""
    out = tmp_path / "leuven.jsonl"
    assert main(["replay", str(LEUVEN), "--max-speed", "--jsonl", str(out)]) == 0
    capsys.readouterr()
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX"]
    assert len(fixes) == 12
    pvt = _receiver_fixes()
    for r in fixes:
        jsonschema.validate(r, SCHEMAS["FIX"])
        rf = r["receiver_fix"]
        assert rf["source"] == "sbf-pvtgeodetic"
        assert rf["age_s"] in (0.0, 1.0)
        assert rf["gpst_tow_s"] == r["gpst_tow_s"] - rf["age_s"]
        theirs = pvt[rf["gpst_tow_s"]]
        assert rf["dist_m"] == pytest.approx(
            np.linalg.norm(np.subtract(r["x_ecef_m"], theirs)), abs=1e-3
        )
        assert rf["dist_m"] < 10.0


def test_android_fix_rows_ride_on_the_records_of_their_epochs():
    """A Fix row among the Beijing log's Raw rows (GnssLogger's layout) is carried on the
    results of the epochs within 1.5 s of it (the first epoch is emitted once the next
    one's rows begin, after the Fix row: age -0.5 s); without a position of ours no
    distance."""
    head = []
    for line in BEIJING.open():
        head.append(line)
        if len(head) > 400:
            break
    raws = [i for i, x in enumerate(head) if x.startswith("Raw,")]
    # 2022-09-28 14:01:28.5 UTC = GPST 14:01:46.5, between the first two epochs (GPST
    # 14:01:46.0 and 47.0)
    head.insert(raws[44], "Fix,GPS,39.9,116.3,50.0,0.0,3.5,1664373688500\n")
    pipe = Pipeline(EphemerisStore())
    results = []
    for ev in GnssLoggerReader(head):
        if isinstance(ev, ReceiverFix):
            pipe.on_receiver_fix(ev)
        elif isinstance(ev, MeasurementEpoch):
            results.append(pipe.on_epoch(ev))
    rf = results[1].receiver_fix
    assert rf is not None and rf.source == "android-gps"
    rec = fix_record(results[1].fix, results[1].since_start_s, rf)
    jsonschema.validate(rec, SCHEMAS["FIX"])
    assert rec["receiver_fix"]["accuracy_m"] == 3.5 and "dist_m" not in rec["receiver_fix"]
    assert rec["receiver_fix"]["age_s"] == pytest.approx(0.5, abs=1e-3)
    assert results[0].receiver_fix is rf  # -0.5 s
    assert all(r.receiver_fix is None for r in results[2:])  # 1.500037 s and later
