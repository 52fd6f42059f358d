"""The status page in a real browser: headless Chromium on ``bdsfix replay`` of the built-in
scenario at real speed (``--output http:127.0.0.1:PORT``), sampled every 0.2 s by
``bench/status_page_shot.py`` (which also makes the README's picture), checked against what
the same replay wrote to its other outputs: the FIX records of its JSONL file, the SKY
records of its ZeroMQ socket and the timeline of its summary. Screenshots are saved (in the
test's directory, or ``$BDSFIX_SCREENSHOTS`` when set)."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import sys
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from service.output.timeline import FULL4
from tests.support.paths import ROOT

pytestmark = [pytest.mark.needs("chromium"), pytest.mark.slow]  # a 60 s replay


def _shot_module():
    spec = importlib.util.spec_from_file_location(
        "status_page_shot", ROOT / "bench/status_page_shot.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


def shown(value: str, record_value: float, digits: int) -> bool:
    """The page's text is the record's value to ``digits`` decimals."""
    return abs(float(value) - record_value) <= 0.5 * 10.0**-digits + 1e-9


FIELDS = (("lat", "lat_deg", 7), ("lon", "lon_deg", 7), ("alt", "alt_m", 2))
OPTIONAL = (
    ("speed", "speed_m_s", 2),
    ("pdop", "pdop", 2),
    ("hpl", "hpl_m", 1),
    ("vpl", "vpl_m", 1),
)


def assert_shows(sample: dict, fix: dict) -> None:
    """The page's fix panel shows this FIX record."""
    assert sample["mode"] == fix["mode"]
    assert sample["tow"] == f"{fix['gpst_tow_s']:.3f}"
    assert sample["week"] == str(fix["gpst_week"])
    assert (sample["full"], sample["frac"]) == (str(fix["n_full"]), str(fix["n_frac"]))
    if fix["mode"] == "none":
        assert sample["reason"] == fix["reason"]
        assert sample["lat"] == sample["lon"] == "–"
        return
    assert sample["reason"] == ""
    for name, key, digits in FIELDS:
        assert shown(sample[name], fix[key], digits), (name, sample[name], fix[key])
    for name, key, digits in OPTIONAL:
        if key in fix:
            assert shown(sample[name], fix[key], digits), (name, sample[name], fix[key])
        else:
            assert sample[name] == "–"
    assert sample["raim"] == fix["raim"]


@pytest.fixture(scope="module")
def watched(tmp_path_factory):
    out = Path(os.environ.get("BDSFIX_SCREENSHOTS") or tmp_path_factory.mktemp("status-page"))
    return _shot_module().watch_replay(out)


def test_the_replay_ran_and_the_page_was_sampled(watched):
    assert watched.returncode == 0, watched.summary
    assert len(watched.fixes) == 600  # 60 s at 10 Hz
    assert len(watched.samples) >= 20  # every 0.2 s of a 60 s replay; fewer on a loaded machine
    for path in watched.screenshots:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {p.name for p in watched.screenshots} >= {"status-page-live.png", "status-page-end.png"}


def test_every_sample_shows_the_fix_record_of_its_epoch(watched):
    by_tow = {f"{f['gpst_tow_s']:.3f}": f for f in watched.fixes}
    checked = 0
    for sample in watched.samples:
        if sample["tow"] == "–":
            continue  # before the first record reached the page
        assert_shows(sample, by_tow[sample["tow"]])
        checked += 1
    assert checked >= 15


def test_the_sky_plot_shows_as_many_satellites_as_the_sky_record(watched):
    by_tow = {f"{s['gpst_tow_s']}": s for s in watched.sky}
    checked = 0
    for sample in watched.samples:
        sky = by_tow.get(sample["sky_tow"] or "")
        if sky is None:
            continue  # a SKY the subscriber joined too late for
        prns = [s["prn"] for s in sky["satellites"]]
        assert sorted(sample["sky_prns"]) == sorted(prns)
        assert sample["sky_count"] == str(len(prns))
        with_cn0 = [s["prn"] for s in sky["satellites"] if "cn0_dbhz" in s]
        assert sample["bars"] == with_cn0
        checked += 1
    assert checked >= 10
    assert len(watched.final["sky_prns"]) == len(watched.sky[-1]["satellites"])


def test_the_fix_mode_turns_fast_at_the_first_fast_fix(watched):
    first = next(i for i, f in enumerate(watched.fixes) if f["mode"] == "fast")
    before = watched.fixes[first - 1]["mode"]
    tow = watched.fixes[first]["gpst_tow_s"]
    # the page's record of its fix modes: none until the first fast fix, fast from it
    changes = watched.final["modes"].split(", ")
    assert f"fast from tow {tow:.3f}" in changes
    k = changes.index(f"fast from tow {tow:.3f}")
    assert changes[k - 1].startswith(f"{before} from tow ")
    assert not any(c.startswith("fast") for c in changes[:k])
    # and no sample showed fast before it
    assert all(
        float(s["tow"]) >= round(tow, 3)
        for s in watched.samples
        if s["mode"] == "fast" and s["tow"] != "–"
    )


def test_the_timeline_equals_the_replay_summary(watched):
    lines = watched.summary.splitlines()
    start = next(i for i, line in enumerate(lines) if "timeline (t: data time since" in line)
    expected = {}
    for line in lines[start + 1 : start + 6]:
        m = re.match(r"  (first .+?)\s{2,}(t = .+ s|\(not reached\))$", line)
        assert m, line
        if m.group(1) != FULL4:  # the summary's alone: taken from every system's ranges
            expected[m.group(1)] = m.group(2)
    assert len(expected) == 4
    assert {k: v.strip() for k, v in watched.final["timeline"].items()} == {
        k: v.strip() for k, v in expected.items()
    }
    assert watched.final["timeline_since"] in lines[start]
    assert "(not reached)" not in expected.values()  # the scenario reaches all four


def test_the_page_at_the_end_shows_the_last_fix_record(watched):
    assert_shows(watched.final, watched.fixes[-1])
    assert watched.final["counters"]["epochs"] == "600"
    assert watched.final["conn"].startswith("disconnected")  # the replay has ended
    assert int(watched.final["scatter_n"]) > 0 and watched.final["scatter_scale"].endswith(" m")


def test_no_request_leaves_loopback(watched):
    origin = urlsplit(watched.url)
    assert watched.requested, "the page's network log is empty"
    pages = [u for u in watched.requested if urlsplit(u).scheme in ("http", "https")]
    assert watched.url in pages and watched.url + "events" in pages
    for url in watched.requested:
        parts = urlsplit(url)
        assert parts.scheme in ("http", "data", "about"), url
        if parts.scheme == "http":
            assert (parts.hostname, parts.port) == (origin.hostname, origin.port), url
    # the browser's own log (NetLog): every request of the page (its navigation, its
    # event stream, anything its script would load) went to the page's host; what else the
    # browser tried is its own (update checks: no origin asked for it, no page's site)
    site = f"{origin.scheme}://{origin.hostname}"
    page_jobs = [
        r
        for r in watched.netlog
        if r["initiator"].startswith(site) or site in r["network_isolation_key"]
    ]
    assert any(r["url"] == watched.url + "events" for r in page_jobs)
    for r in page_jobs:
        assert urlsplit(r["url"]).hostname == origin.hostname, r
    for r in watched.netlog:
        if urlsplit(r["url"]).hostname != origin.hostname:
            assert r["initiator"] == "not an origin" and site not in r["network_isolation_key"], r
    print(
        "browser's own requests:",
        sorted({r["url"].split("?")[0] for r in watched.netlog if r not in page_jobs}),
    )


def test_screenshots_are_kept(watched, tmp_path):
    keep = os.environ.get("BDSFIX_SCREENSHOTS")
    if keep:
        assert all(Path(keep) in p.parents for p in watched.screenshots)
    else:  # the test's own directory, kept by pytest for the last runs
        assert all(p.exists() for p in watched.screenshots)
    shutil.copy(watched.screenshots[-1], tmp_path / "copy.png")
