"""``Runner.inline``: a capture file replayed at full speed is read in the loop's own thread.

The inline loop must publish exactly what the loop with its reader thread publishes (the
same sentences, records and counters for a real capture), report a source's failure the
same way (after the events before it, with the final STATUS), and ``bdsfix replay`` must
use it only for a regular file at full speed.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.source import open_source
from service.core.ephemeris import EphemerisStore
from service.daemon.loop import Runner
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from service.output.sinks.lines import JsonlSink, NmeaFileSink
from tests.support.paths import DATA, ROOT

CAPTURE = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
NAV = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"
TIMING = ("epoch_loop_", "epoch_publish_")


class Statuses(Publishers):
    """Publishers that also keep every STATUS's counters (the loop's timings left out)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.statuses: list[dict] = []

    def status(self, counters, **extra) -> None:
        self.statuses.append({k: v for k, v in counters.items() if not k.startswith(TIMING)})
        super().status(counters, **extra)


def replay(tmp_path: Path, inline: bool) -> tuple[bytes, bytes, int, dict]:
    nmea, jsonl = tmp_path / f"{inline}.nmea", tmp_path / f"{inline}.jsonl"
    outputs = Statuses([NmeaFileSink(str(nmea)), JsonlSink(str(jsonl))])
    with open_source(str(CAPTURE), nav=str(NAV)) as src:
        runner = Runner(
            src,
            Pipeline(EphemerisStore()),
            outputs,
            source_counters=src.counters,
            status_interval_s=1e9,
            inline=inline,
        )
        n = runner.run()
    outputs.close()
    return nmea.read_bytes(), jsonl.read_bytes(), n, outputs.statuses[-1]


def test_inline_loop_publishes_what_the_reader_thread_loop_publishes(tmp_path):
    threaded = replay(tmp_path, inline=False)
    inline = replay(tmp_path, inline=True)
    assert threaded[2] == inline[2] == 196  # the capture's RAWX epochs
    assert inline[0] == threaded[0] and inline[0].count(b"GGA,") == 196
    assert inline[1] == threaded[1]
    assert inline[3] == threaded[3]


class Broken(Exception):
    pass


def failing_source(k: int) -> Iterator[object]:
    """The capture's first ``k`` events, then a failure of the source."""
    with open_source(str(CAPTURE), nav=str(NAV)) as src:
        for i, ev in enumerate(src):
            if i == k:
                raise Broken("the source failed")
            yield ev


@pytest.mark.parametrize("inline", [False, True])
def test_a_source_failure_is_raised_after_the_events_before_it_and_the_final_status(
    tmp_path, inline
):
    outputs = Statuses([NmeaFileSink(str(tmp_path / "out.nmea"))])
    seen = []
    runner = Runner(
        failing_source(200),
        Pipeline(EphemerisStore()),
        outputs,
        status_interval_s=1e9,
        inline=inline,
        on_result=seen.append,
    )
    with pytest.raises(Broken, match="the source failed"):
        runner.run()
    assert seen, "epochs before the failure are published"
    assert outputs.statuses and outputs.statuses[-1]["epochs"] == len(seen)


def run_replay(*args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess[bytes]:
    """``python -m service replay ARGS`` with the loop's thread set-up printed at its end."""
    code = (
        "import sys, threading\n"
        "from service.daemon.loop import Runner\n"
        "from service.commands.cli import main\n"
        "run = Runner.run\n"
        "def spy(self):\n"
        "    n = run(self)\n"
        "    print('inline' if self.inline else 'threaded', file=sys.stderr)\n"
        "    return n\n"
        "Runner.run = spy\n"
        f"sys.exit(main(['replay', *{list(args)!r}]))\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, input=stdin, capture_output=True, check=True
    )


def loop_kind(proc: subprocess.CompletedProcess[bytes]) -> list[str]:
    return [x for x in proc.stderr.decode().splitlines() if x in ("inline", "threaded")]


def test_replay_reads_inline_only_a_regular_file_at_full_speed():
    fast = run_replay(str(CAPTURE), "--max-speed", "--nmea-out", "/dev/null")
    assert loop_kind(fast) == ["inline"]
    piped = run_replay("-", "--max-speed", "--nmea-out", "/dev/null", stdin=CAPTURE.read_bytes())
    assert loop_kind(piped) == ["threaded"]
    paced = run_replay(str(CAPTURE), "--speed", "1000", "--nmea-out", "/dev/null")
    assert loop_kind(paced) == ["threaded"]
