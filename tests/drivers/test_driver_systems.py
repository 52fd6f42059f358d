"""Drivers name each satellite by its system (issue 18): u-blox gnssId through one table,
checked against pyubx2's own; on a real multi-GNSS capture only BeiDou IDs come out and the
other systems' measurements are counted, as many as pyubx2 finds in the same bytes."""

from __future__ import annotations

import io
from collections import Counter

from pyubx2 import GNSSLIST, UBX_PROTOCOL, UBXReader

from drivers.sfrbx import UBX_GNSS
from drivers.source import StreamDecoder
from service.core.systems import GnssSystem, system_of
from service.core.types import MeasurementEpoch, NavSubframe
from tests.support.paths import DATA

POLYU = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"


def test_ubx_gnss_table_agrees_with_pyubx2():
    names = {
        "GPS": GnssSystem.GPS,
        "SBAS": GnssSystem.SBAS,
        "Galileo": GnssSystem.GAL,
        "BeiDou": GnssSystem.BDS,
        "QZSS": GnssSystem.QZS,
        "GLONASS": GnssSystem.GLO,
        "NAVIC": GnssSystem.IRN,
    }
    assert {k: names[v] for k, v in GNSSLIST.items() if v in names} == UBX_GNSS
    assert GNSSLIST[4] == "IMES" and 4 not in UBX_GNSS  # no satellite system


def test_real_capture_gives_beidou_ids_and_counts_the_other_systems():
    data = POLYU.read_bytes()
    other = Counter()
    bds_rawx = 0
    for _, msg in UBXReader(io.BytesIO(data), protfilter=UBX_PROTOCOL, quitonerror=0):
        if msg is None or getattr(msg, "identity", "") != "RXM-RAWX":
            continue
        for i in range(1, int(msg.numMeas) + 1):
            gnss = int(getattr(msg, f"gnssId_{i:02d}"))
            if gnss == 3:
                bds_rawx += 1
            else:
                other[gnss] += 1
    assert bds_rawx > 0 and other[0] > 0, (bds_rawx, other)  # the capture has GPS too

    dec = StreamDecoder()
    events = dec.feed(data) + dec.flush()
    sats = {p for e in events if isinstance(e, MeasurementEpoch) for p in e.prn}
    sats |= {e.prn for e in events if isinstance(e, NavSubframe)}
    assert sats and {system_of(p) for p in sats} == {GnssSystem.BDS}
    assert dec.counters["rawx_meas_other_gnss"] == sum(other.values())
