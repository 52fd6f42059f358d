"""Headless Chromium driven through the DevTools protocol over a pipe
(``--remote-debugging-pipe``: commands on the browser's fd 3, answers and events on its fd
4, each message JSON ended by a NUL byte), standard library only: no websocket, no port.

The page's network log is the protocol's ``Network.requestWillBeSent`` events of its
session; the whole browser's is Chromium's own NetLog (``--log-net-log``), written when the
browser closes. Background networking (updates, sync, metrics) is switched off so that what
the log holds is mostly what the page asked for; what the browser still tries on its own
(update checks) resolves nowhere (``--host-resolver-rules``), and the NetLog tells it apart
(its ``initiator`` is ``not an origin``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Any

CHROMIUM = "chromium"


class BrowserError(Exception):
    pass


class Chromium:
    """One headless browser with one page (a tab) attached."""

    def __init__(self, width: int = 1400, height: int = 1000, log_dir: Path | None = None):
        exe = shutil.which(CHROMIUM)
        if exe is None:
            raise BrowserError("chromium is not installed (Debian: apt-get install chromium)")
        self.dir = Path(tempfile.mkdtemp(prefix="bdsfix-chromium-"))
        self.netlog = (log_dir or self.dir) / "netlog.json"
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        log = os.open(self.dir / "chromium.log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        args = [
            exe,
            "--headless",
            "--no-sandbox",  # as root in CI
            "--disable-gpu",
            "--remote-debugging-pipe",
            f"--user-data-dir={self.dir / 'profile'}",
            f"--log-net-log={self.netlog}",
            "--no-first-run",
            "--no-default-browser-check",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-default-apps",
            "--disable-extensions",
            "--disable-sync",
            "--disable-domain-reliability",
            "--metrics-recording-only",
            "--no-pings",
            # the browser's own background requests (update checks, its clock) resolve
            # nowhere: only loopback is reachable from this browser
            "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
            "--disable-features=NetworkTimeServiceQuerying,OptimizationHints,MediaRouter,"
            "Translate,AutofillServerCommunication",
            f"--window-size={width},{height}",
            "about:blank",
        ]
        self.pid = os.posix_spawn(
            exe,
            args,
            os.environ,
            file_actions=[
                (os.POSIX_SPAWN_DUP2, to_browser_r, 3),
                (os.POSIX_SPAWN_DUP2, from_browser_w, 4),
                (os.POSIX_SPAWN_DUP2, log, 1),
                (os.POSIX_SPAWN_DUP2, log, 2),
            ],
        )
        for fd in (to_browser_r, from_browser_w, log):
            os.close(fd)
        self._next_id = 0
        self._answers: dict[int, dict[str, Any]] = {}
        self.events: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self._eof = False
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)[
            "sessionId"
        ]
        for domain in ("Page", "Network", "Runtime"):
            self.call(f"{domain}.enable", session=True)
        self.call(
            "Emulation.setDeviceMetricsOverride",
            session=True,
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_browser, 1 << 20)
            except OSError:
                chunk = b""
            if not chunk:
                with self._cond:
                    self._eof = True
                    self._cond.notify_all()
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                with self._cond:
                    if "id" in msg:
                        self._answers[msg["id"]] = msg
                    else:
                        self.events.append(msg)
                    self._cond.notify_all()

    def call(self, method: str, session: bool = False, **params: Any) -> dict[str, Any]:
        """One protocol command; its result (BrowserError for an error answer)."""
        with self._cond:
            self._next_id += 1
            n = self._next_id
        msg: dict[str, Any] = {"id": n, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_browser, json.dumps(msg).encode() + b"\0")
        with self._cond:
            # a generous bound against a browser that hangs, not a timing
            self._cond.wait_for(lambda: n in self._answers or self._eof, timeout=120)
            answer = self._answers.pop(n, None)
        if answer is None:
            raise BrowserError(f"{method}: no answer from chromium (see {self.dir}/chromium.log)")
        if "error" in answer:
            raise BrowserError(f"{method}: {answer['error']}")
        return dict(answer.get("result", {}))

    def navigate(self, url: str) -> None:
        """Open ``url`` and wait for its load event (the page's script has run)."""
        with self._cond:
            seen = len(self.events)
        self.call("Page.navigate", session=True, url=url)
        with self._cond:
            loaded = self._cond.wait_for(
                lambda: (
                    any(e.get("method") == "Page.loadEventFired" for e in self.events[seen:])
                    or self._eof
                ),
                timeout=120,  # a hang guard, not a timing
            )
        if not loaded or self._eof:
            raise BrowserError(f"{url}: the page did not load")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page."""
        result = self.call(
            "Runtime.evaluate", session=True, expression=expression, returnByValue=True
        )
        if "exceptionDetails" in result:
            raise BrowserError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def screenshot(self, path: Path) -> Path:
        data = self.call("Page.captureScreenshot", session=True, format="png")["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def requested_urls(self) -> list[str]:
        """Every URL the page asked for (its network log)."""
        with self._cond:
            return [
                e["params"]["request"]["url"]
                for e in self.events
                if e.get("method") == "Network.requestWillBeSent"
            ]

    def close(self) -> None:
        """Close the browser (it writes its NetLog) and wait for it."""
        with contextlib.suppress(BrowserError, OSError):
            self.call("Browser.close")
        with self._cond:
            closed = self._cond.wait_for(lambda: self._eof, timeout=60)
        if not closed:  # a browser that does not close: ours, by its pid
            os.kill(self.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        for fd in (self._to_browser, self._from_browser):
            with contextlib.suppress(OSError):
                os.close(fd)

    def netlog_requests(self) -> list[dict[str, Any]]:
        """Every request job in the browser's NetLog (after :meth:`close`): ``url``,
        ``initiator`` (the origin that asked, ``not an origin`` for the browser's own
        requests) and ``network_isolation_key`` (the top frame's site of a page's request)."""
        if not self.netlog.exists():
            raise BrowserError(f"chromium wrote no NetLog at {self.netlog}")
        text = self.netlog.read_text()
        try:
            log = json.loads(text)
        except json.JSONDecodeError:  # a log cut after its last event
            log = json.loads(text.rstrip().rstrip(",") + "]}")
        start_job = log["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
        return [
            {k: str(ev["params"].get(k, "")) for k in ("url", "initiator", "network_isolation_key")}
            for ev in log.get("events", [])
            if ev.get("type") == start_job and "url" in (ev.get("params") or {})
        ]
