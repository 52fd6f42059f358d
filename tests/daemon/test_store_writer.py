"""The store writer thread: the loop hands it a snapshot and goes on; the newest snapshot
wins; close() writes the last one before it returns; a failed write is retried."""

from __future__ import annotations

import threading

from service.core.ephemeris import EphemerisStore, StoreSnapshot
from service.daemon.store_writer import StoreWriter
from service.sim.keplerian import table1_ephemerides


class _SlowDisk:
    """A write function that blocks until released and records what it wrote."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()
        self.written: list[int] = []
        self.fail = False

    def __call__(self, path, snapshot: StoreSnapshot) -> None:
        self.started.set()
        assert self.release.wait(30)
        if self.fail:
            raise OSError(28, "No space left on device")
        self.written.append(len(snapshot))


def _snap(n: int) -> StoreSnapshot:
    return StoreSnapshot(tuple(table1_ephemerides(0.0)[:n]))


def test_submit_returns_while_the_disk_is_slow_and_the_newest_snapshot_wins(tmp_path):
    disk = _SlowDisk()
    writer = StoreWriter(tmp_path / "ephemeris.json", write=disk)
    writer.submit(_snap(1))
    assert disk.started.wait(30)  # the first write is under way, blocked on the disk
    writer.submit(_snap(2))  # returns at once: waits behind the write in progress
    writer.submit(_snap(3))  # replaces the one waiting
    assert disk.written == []
    disk.release.set()
    assert writer.idle(30)
    assert disk.written == [1, 3] and writer.saves == 2
    writer.close(_snap(4))  # the shutdown save: written before close returns
    assert disk.written == [1, 3, 4] and writer.closed


def test_a_failed_write_is_counted_and_flagged_then_retried(tmp_path, caplog):
    disk = _SlowDisk()
    disk.release.set()
    disk.fail = True
    writer = StoreWriter(tmp_path / "ephemeris.json", write=disk)
    writer.submit(_snap(1))
    assert writer.idle(30)
    assert writer.failed and writer.save_errors == 1 and "No space left" in caplog.text
    disk.fail = False
    writer.submit(_snap(2))
    assert writer.idle(30)
    assert not writer.failed and disk.written == [2]
    writer.close()


def test_close_without_a_thread_writes_in_the_caller(tmp_path):
    path = tmp_path / "ephemeris.json"
    StoreWriter(path).close(_snap(5))
    assert len(EphemerisStore.load(path)) == 5
