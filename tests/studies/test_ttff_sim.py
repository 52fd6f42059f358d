"""``bdsfix ttff --simulate``: the ~1 s first fix measured through the whole stream path.

Each run streams restarts of the virtual receiver (UBX at 10 Hz) through a real pty into a
``bdsfix run`` process that reads it with pyserial; TTFF comes from the daemon's JSONL.
Five places inside the >= 4-GEO area, 20 restarts each, with the paper's Table 1
constellation; one place outside it (40 N 10 W) with the 2024 broadcast constellation of
``hksc269h.24f``, where only one GEO is in view.

The simulated receiver holds a satellite full after one complete subframe read after bit
sync (D2 0.6 s, D1 6 s), subframe boundaries from BDT. For the GEOs the first fix then comes
at the first 0.6 s boundary after acquisition and sync (~0.1 s), plus 0.6 s, rounded up to
the next 0.1 s epoch: uniform over about 0.7-1.3 s, whose median is 1.0 s. The issue's
"median <= 1.0 s" therefore sits on the model's own median; with these seeds (the run is
deterministic) the 100 trials give 1.00 s.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.support.paths import ROOT

DATA = ROOT.parent / "shared" / "data"
BDSFIX = [sys.executable, "-m", "service"]

INSIDE = {
    "Beijing": (39.9, 116.4),
    "Hong Kong": (22.3, 114.2),
    "Sydney": (-33.87, 151.21),
    "Tokyo": (35.68, 139.69),
    "Singapore": (1.35, 103.82),
}
SIGMA_M = 1.3


def _ttff(lat: float, lon: float, trials: int, seed: int, *extra: str) -> subprocess.Popen:
    cmd = [
        *BDSFIX,
        "ttff",
        "--simulate",
        "--json",
        "--lat-deg",
        str(lat),
        "--lon-deg",
        str(lon),
        "--trials",
        str(trials),
        "--seed",
        str(seed),
        "--rate-hz",
        "10",
        "--noise-m",
        str(SIGMA_M),
        "--elmask-deg",
        "5",
        *extra,
    ]
    return subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, err[-2000:]
    assert "Traceback" not in err
    return json.loads(out)


@pytest.mark.slow
def test_simulated_streams_through_a_pty_give_the_fast_first_fix():
    # all five at once: the machine's two cores share them; times are data times
    procs = {
        name: _ttff(lat, lon, 20, 7 + k) for k, (name, (lat, lon)) in enumerate(INSIDE.items())
    }
    docs = {name: _result(p) for name, p in procs.items()}
    fast_all, conv_all = [], []
    lines = []
    for name, doc in docs.items():
        assert doc["trials"] == 20
        assert doc["fast"]["success_pct"] == 100.0, (name, doc["fast"])
        assert doc["conventional"]["success_pct"] == 100.0, (name, doc["conventional"])
        assert doc["conventional"]["median_s"] >= 6.0, (name, doc["conventional"])
        # every fast fix is the SPP fix of the true full ranges (paper eq. 16) ...
        assert doc["fast"]["fixes"] > 20 * 40
        assert doc["fast"]["max_diff_to_spp_m"] <= 1e-3, name
        # ... and its error is consistent with the range noise
        assert doc["fast"]["max_err_over_sigma_pdop"] <= 5.0, name
        fast_all += [t["fast_s"] for t in doc["per_trial"]]
        conv_all += [t["conventional_s"] for t in doc["per_trial"]]
        lines.append(
            f"{name}: fast median {doc['fast']['median_s']:.2f} s p95 {doc['fast']['p95_s']:.2f}"
            f" s, conventional median {doc['conventional']['median_s']:.2f} s, max |fast-SPP| "
            f"{doc['fast']['max_diff_to_spp_m'] * 1e3:.3f} mm, max err/(sigma PDOP) "
            f"{doc['fast']['max_err_over_sigma_pdop']:.2f}"
        )
    fast_med, fast_p95 = float(np.median(fast_all)), float(np.percentile(fast_all, 95))
    conv_med = float(np.median(conv_all))
    print("\n".join(lines))
    print(
        f"all 100 trials: fast median {fast_med:.2f} s, p95 {fast_p95:.2f} s; conventional "
        f"median {conv_med:.2f} s; ratio {conv_med / fast_med:.1f}"
    )
    assert fast_med <= 1.0  # see the module docstring
    assert fast_p95 <= 1.5
    assert conv_med >= 6.0


def test_outside_the_geo_area_the_fast_fix_declines_and_conventional_fixes():
    nav = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"
    doc = _result(_ttff(40.0, -10.0, 4, 3, str(nav), "--max-eph-age-s", "43200"))
    assert doc["conventional"]["success_pct"] == 100.0
    assert doc["conventional"]["median_s"] >= 6.0
    # no fast fix while measurements are fractional: with one GEO in view it waits for D1
    assert doc["fast"]["success_pct"] == 0.0
    reasons = doc["fast"]["declined_before_first_fix"]
    assert reasons and all(r.startswith("too few full measurements") for r in reasons), reasons
