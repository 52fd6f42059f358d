"""One input registry: a new binary protocol and a new text file format are each one module
(tests/support/toy_protocol.py, tests/support/toy_text.py) plus one registry line.

Both toys carry real measurements: the first epochs of the HKSC RINEX obs file. Read back
through the registry they give the same epochs, and the engine the same fixes, as the
RINEX file itself.
"""

from __future__ import annotations

import itertools
import subprocess
import sys

import numpy as np
import pytest

from drivers import protocols
from drivers.protocols import FileFormat, ProtocolSpec
from drivers.rinex import read_nav
from drivers.source import check_capture, expected_inputs, open_source
from service.core.ephemeris import EphemerisStore
from service.core.errors import InputError
from service.core.types import MeasurementEpoch
from service.engine.pipeline import Pipeline
from tests.support import toy_protocol, toy_text
from tests.support.paths import DATA, ROOT

OBS = DATA / "hksc-2021" / "hksc1610.obs"
NAV = DATA / "hksc-2021" / "hksc1610.nav"
N_EPOCHS = 8


def _rinex_epochs() -> list[MeasurementEpoch]:
    """The first epochs of the obs file, with what the toys carry: the pseudoranges (no
    C/N0, whose weights would move the fixes by centimetres)."""
    with open_source(str(OBS)) as src:
        read = [e for e in itertools.islice(src, N_EPOCHS) if isinstance(e, MeasurementEpoch)]
    return [
        MeasurementEpoch.from_columns(e.gpst_week, e.gpst_tow_s, e.prn, e.signal, e.pr_m)
        for e in read
    ]


def _fixes(epochs: list[MeasurementEpoch]) -> list[np.ndarray]:
    pipe = Pipeline(EphemerisStore())
    for ephs in read_nav(NAV).ephemerides.values():
        for eph in ephs:
            pipe.add_ephemeris(eph)
    fixes = [pipe.on_epoch(e).fix for e in epochs]
    assert all(f.ok for f in fixes)
    return [np.asarray(f.x_ecef_m) for f in fixes]


def _same_epochs(got: list[MeasurementEpoch], want: list[MeasurementEpoch]) -> None:
    assert len(got) == len(want) == N_EPOCHS
    for g, w in zip(got, want, strict=True):
        assert (g.gpst_week, g.gpst_tow_s, g.prn) == (w.gpst_week, w.gpst_tow_s, w.prn)
        np.testing.assert_array_equal(g.pr_m, w.pr_m)


def test_a_toy_binary_protocol_is_one_module_and_one_registry_line(tmp_path, monkeypatch):
    want = _rinex_epochs()
    capture = tmp_path / "toy.bin"
    nmea = b"$GPGGA,,,,,,0,,,,,,,,*66\r\n"  # a registered protocol in the same stream
    capture.write_bytes(b"".join(nmea + toy_protocol.encode(e) for e in want))
    with open_source(str(capture)) as src:  # before: the toy frames are skipped bytes
        assert not any(isinstance(e, MeasurementEpoch) for e in src)
        assert src.counters["bytes_skipped"] > 0
    # the registry line:
    spec = ProtocolSpec("toy", toy_protocol.FRAMING, toy_protocol.ToyMapper)
    monkeypatch.setattr(protocols, "PROTOCOLS", (*protocols.PROTOCOLS, spec))
    check_capture(capture)
    assert "TOY" in expected_inputs()
    with open_source(str(capture)) as src:
        got = [e for e in src if isinstance(e, MeasurementEpoch)]
        counters = src.counters
    _same_epochs(got, want)
    assert counters["frames_toy"] == counters["epochs_toy"] == N_EPOCHS
    assert counters["frames_nmea"] == N_EPOCHS
    assert counters["bytes_skipped"] == 0
    for a, b in zip(_fixes(got), _fixes(want), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_toy_text_format_is_one_module_and_one_registry_line(tmp_path, monkeypatch):
    want = _rinex_epochs()
    path = tmp_path / "epochs.toy"
    toy_text.write(path, want)
    with pytest.raises(InputError, match="no frame found"):
        check_capture(path)
    # the registry line:
    fmt = FileFormat("toytext", "a toy text file", toy_text.detect, toy_text.events)
    monkeypatch.setattr(protocols, "FILE_FORMATS", (*protocols.FILE_FORMATS, fmt))
    check_capture(path)
    assert expected_inputs().endswith("or a toy text file")
    for spec in (str(path), f"toytext:{path}"):  # detected by content, or named by scheme
        with open_source(spec) as src:
            got = [e for e in src if isinstance(e, MeasurementEpoch)]
            assert src.counters["epochs_toytext"] == src.counters["events"] == N_EPOCHS
        _same_epochs(got, want)
    for a, b in zip(_fixes(got), _fixes(want), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_scheme_names_the_format_whatever_the_content(tmp_path):
    """``gnsslogger:PATH`` reads PATH as a GnssLogger log even without its header: the
    rows alone (the first 30 Raw rows of the Perth log, whose header is stripped)."""
    perth = DATA / "android-perth-s8-2017" / "SensorLog20171005.txt"
    rows = [x for x in perth.open() if x.startswith("Raw,")][:30]
    path = tmp_path / "rows.txt"
    path.write_text("".join(rows))
    with open_source(f"gnsslogger:{path}") as src:
        got = [e for e in src if isinstance(e, MeasurementEpoch)]
    assert len(got) == 3 and got[0].prn[0] == "G02"


def test_a_rinex_file_is_read_without_the_stream_protocols(tmp_path):
    """``bdsfix solve`` of a RINEX file frames no stream: reading it through the registry
    (drivers.source.file_epochs) imports none of the stream protocols' modules or their
    libraries; reading ``PROTOCOLS`` brings them (a fresh interpreter, as at start-up)."""
    code = (
        "import sys\n"
        "from drivers.source import file_epochs\n"
        f"events, _ = file_epochs({str(OBS)!r})\n"
        "n = sum(1 for _ in events)\n"
        "libs = ('pyubx2', 'pyrtcm', 'pysbf2', 'pynmeagps', 'drivers.ubx', 'drivers.rtcm',\n"
        "        'drivers.sbf', 'drivers.nmea')\n"
        "print(n, [m for m in libs if m in sys.modules])\n"
        "from drivers.protocols import PROTOCOLS\n"
        "print([p.name for p in PROTOCOLS], [m for m in libs if m not in sys.modules])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout.splitlines()
    assert out == ["205 []", "['ubx', 'rtcm', 'sbf', 'nmea'] []"]
