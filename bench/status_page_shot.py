"""The status page of ``bdsfix replay`` (the built-in scenario, at real speed) in headless
Chromium: what the page showed along the way, its network log, and screenshots.

``python bench/status_page_shot.py`` writes ``docs/status-page.png`` (the README's picture).
``tests/system/test_status_page.py`` runs :func:`watch_replay` and checks what the page
showed against the replay's own records and summary.

The replay publishes its records to the page (``--output http:127.0.0.1:PORT``), to a JSONL
file (FIX and TRACK) and to ZeroMQ (SKY is read from there); the browser opens the page as
soon as the port answers and is sampled (one JavaScript expression reading the page's
elements) until the replay exits, then once more.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.support.browser import Chromium  # noqa: E402

SAMPLE = """(() => {
  const t = (id) => document.getElementById(id).textContent;
  const rows = [...document.querySelectorAll("#timeline tr")];
  return {
    conn: t("conn"), since: t("fix-since"), mode: t("fix-mode"), reason: t("fix-reason"),
    week: t("fix-week"),
    tow: t("fix-tow"), lat: t("fix-lat"), lon: t("fix-lon"), alt: t("fix-alt"),
    speed: t("fix-speed"), pdop: t("fix-pdop"), hpl: t("fix-hpl"), vpl: t("fix-vpl"),
    raim: t("fix-raim"), full: t("fix-full"), frac: t("fix-frac"),
    sky_tow: document.getElementById("sky").getAttribute("data-tow"),
    sky_prns: [...document.querySelectorAll("#sky g.sat")].map((g) => g.getAttribute("data-prn")),
    sky_count: t("sky-count"),
    bars: [...document.querySelectorAll("#cn0 rect.bar")].map((r) => r.getAttribute("data-prn")),
    timeline: Object.fromEntries(rows.map((r) => [r.getAttribute("data-key"),
      r.querySelector("td.t").textContent])),
    timeline_since: t("timeline-since"),
    modes: t("modes-text"),
    scatter_n: t("scatter-n"), scatter_scale: t("scatter-scale"),
    counters: Object.fromEntries([...document.querySelectorAll("#counters-table tr")].map(
      (r) => [r.getAttribute("data-counter"), r.querySelector("td.num").textContent])),
  };
})()"""


@dataclass
class Watched:
    """What :func:`watch_replay` saw."""

    url: str
    samples: list[dict[str, Any]]
    final: dict[str, Any]
    fixes: list[dict[str, Any]]
    sky: list[dict[str, Any]]
    summary: str
    requested: list[str]
    netlog: list[dict[str, str]]
    screenshots: list[Path] = field(default_factory=list)
    returncode: int = 0


LIVE_SHOT_S = 50.0
"""Data time of the live screenshot (the scenario lasts 60 s) [s]."""


def _since(sample: dict[str, Any]) -> float:
    try:
        return float(sample["since"])
    except ValueError:
        return -1.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _collect_sky(endpoint: str, out: list[dict[str, Any]], stop: threading.Event) -> None:
    import zmq

    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"SKY")
    sub.setsockopt(zmq.RCVTIMEO, 200)
    sub.connect(endpoint)
    try:
        while not stop.is_set():
            try:
                _topic, body = sub.recv_multipart()
            except zmq.Again:
                continue
            out.append(json.loads(body))
    finally:
        sub.close(linger=0)
        ctx.term()


def watch_replay(
    out_dir: Path, python: str = sys.executable, seconds_between: float = 0.2
) -> Watched:
    """Run the replay and the browser; sample the page until the replay ends."""
    out_dir.mkdir(parents=True, exist_ok=True)
    port, zmq_port = _free_port(), _free_port()
    url = f"http://127.0.0.1:{port}/"
    jsonl = out_dir / "replay.jsonl"
    browser = Chromium(log_dir=out_dir)
    sky: list[dict[str, Any]] = []
    stop = threading.Event()
    endpoint = f"tcp://127.0.0.1:{zmq_port}"
    sub = threading.Thread(target=_collect_sky, args=(endpoint, sky, stop), daemon=True)
    sub.start()
    proc = subprocess.Popen(
        [
            python,
            "-m",
            "service",
            "replay",
            "--speed",
            "1",
            "--output",
            f"http:127.0.0.1:{port}",
            "--zmq",
            endpoint,
            "--jsonl-out",
            str(jsonl),
            "--status-interval-s",
            "1",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    samples: list[dict[str, Any]] = []
    shots: list[Path] = []
    try:
        while proc.poll() is None:  # the page is served once the replay has bound its port
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.02)
        browser.navigate(url)
        saw_fast = saw_late = False
        while proc.poll() is None:
            sample = browser.evaluate(SAMPLE)
            samples.append(sample)
            if sample["mode"] == "fast" and not saw_fast:
                saw_fast = True
                shots.append(browser.screenshot(out_dir / "status-page-fast.png"))
            if _since(sample) >= LIVE_SHOT_S and not saw_late:
                saw_late = True  # live, near the end: the README's picture
                shots.append(browser.screenshot(out_dir / "status-page-live.png"))
            time.sleep(seconds_between)
        summary = proc.stderr.read() if proc.stderr else ""
        proc.wait()
        # the stream's end reaches the page after its last events (EventSource dispatches
        # in order): the page says so once it has shown everything the replay sent
        final = browser.evaluate(SAMPLE)
        end = time.monotonic() + 60.0  # a hang guard, not a timing
        while not final["conn"].startswith("disconnected") and time.monotonic() < end:
            time.sleep(0.05)
            final = browser.evaluate(SAMPLE)
        shots.append(browser.screenshot(out_dir / "status-page-end.png"))
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait()
        stop.set()
        sub.join(timeout=5)
        requested = browser.requested_urls()
        browser.close()
    netlog = browser.netlog_requests()
    fixes = [r for r in map(json.loads, jsonl.read_text().splitlines()) if r["class"] == "FIX"]
    return Watched(
        url, samples, final, fixes, sky, summary, requested, netlog, shots, proc.returncode
    )


def main() -> None:
    import tempfile

    out = Path(tempfile.mkdtemp(prefix="bdsfix-status-page-"))
    watched = watch_replay(out)
    live = [p for p in watched.screenshots if p.name == "status-page-live.png"]
    if not live:
        raise SystemExit(f"no live screenshot was taken (see {out})")
    target = ROOT / "docs" / "status-page.png"
    os.replace(live[0], target)
    print(f"{target}: the page {LIVE_SHOT_S:g} s into the built-in scenario's replay")


if __name__ == "__main__":
    main()
