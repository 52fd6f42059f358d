"""The time-to-first-fix timeline from the records (what the status page shows) equals the
one from the pipeline's results (what the replay summary prints), with and without an
emulated restart, on the built-in scenario through the real loop."""

from __future__ import annotations

import pytest

from service.commands.run import decode_chunks
from service.daemon.loop import Runner
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from service.output.sinks.base import RECORD_CLASSES, Sink
from service.output.timeline import FULL4, ORDER, Timeline
from service.sim.scenario import builtin_scenario


class RecordTimeline(Sink):
    records = frozenset(RECORD_CLASSES)

    def __init__(self, offset_s: float) -> None:
        self.timeline = Timeline(offset_s)
        self.n = 0

    def write_record(self, cls, record) -> None:
        self.n += 1
        self.timeline.on_record(cls, record)


@pytest.mark.parametrize("restart_at_s", [None, 20.0])
def test_records_give_the_summary_timeline(restart_at_s):
    chunks, week, store, iono, offset, _info = builtin_scenario()
    from_results = Timeline(offset)
    sink = RecordTimeline(offset)
    runner = Runner(
        decode_chunks(chunks, week),
        Pipeline(store, iono, restart_at_s=restart_at_s),
        Publishers([sink]),
        status_interval_s=1e9,
        on_result=from_results.on_result,
    )
    assert runner.run() == 600
    restarted = restart_at_s is not None
    # every event the page shows (the summary adds "first 4 full ranges", which it takes
    # from the epochs' ranges of every system: the records carry the used ones only)
    assert sink.timeline.figures() == from_results.figures()
    page = sink.timeline.lines(restarted=restarted)
    assert [x for x in from_results.lines(restarted=restarted) if FULL4 not in x] == [
        x for x in page if FULL4 not in x
    ]
    assert sink.timeline.restarted is restarted
    figures = sink.timeline.figures()
    assert list(figures) == list(ORDER) and None not in figures.values()
    # the restarted receiver's timeline: its first events come after the restart again
    assert figures["first fast fix"] < 10.0
