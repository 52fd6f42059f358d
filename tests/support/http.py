"""Plain-socket HTTP for the status page's tests: one request and its whole answer, and a
Server-Sent Events reader that parses what it receives (standard library only, so the
tests see the bytes the server sends)."""

from __future__ import annotations

import contextlib
import json
import socket
import threading
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes


def request(address: tuple[str, int], raw: bytes) -> Answer:
    """Send ``raw`` (a whole request head) and read until the server closes."""
    with socket.create_connection(address) as s:
        s.sendall(raw)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split(" ")[1])
    headers = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    return Answer(status, headers, body)


def get(address: tuple[str, int], target: str, method: str = "GET", host: str = "") -> Answer:
    host = host or f"{address[0]}:{address[1]}"
    return request(address, f"{method} {target} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())


@dataclass
class SseReader:
    """Reads ``/events`` in a thread and keeps every event (name, parsed data)."""

    address: tuple[str, int]
    events: list[tuple[str, Any]] = field(default_factory=list)
    cond: threading.Condition = field(default_factory=threading.Condition)
    closed: bool = False

    def __post_init__(self) -> None:
        self.sock = socket.create_connection(self.address)
        host = f"{self.address[0]}:{self.address[1]}"
        self.sock.sendall(f"GET /events HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        buf = b""
        head_done = False
        while True:
            try:
                chunk = self.sock.recv(65536)
            except OSError:
                chunk = b""
            if not chunk:
                with self.cond:
                    self.closed = True
                    self.cond.notify_all()
                return
            buf += chunk
            if not head_done:
                if b"\r\n\r\n" not in buf:
                    continue
                buf = buf.split(b"\r\n\r\n", 1)[1]
                head_done = True
            while b"\n\n" in buf:
                block, buf = buf.split(b"\n\n", 1)
                name, data = "message", ""
                for line in block.decode().split("\n"):
                    if line.startswith("event: "):
                        name = line[7:]
                    elif line.startswith("data: "):
                        data += line[6:]
                if data:
                    with self.cond:
                        self.events.append((name, json.loads(data)))
                        self.cond.notify_all()

    def wait_for(self, pred: Any, timeout_s: float = 120.0) -> bool:
        """Wait (a generous bound, not a timing) until ``pred(events)`` holds or the stream
        ended; whether it holds."""
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.events) or self.closed, timeout_s) and bool(
                pred(self.events)
            )

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the thread's recv
        self.sock.close()
        self.thread.join(timeout=5)
