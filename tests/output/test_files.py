"""Output files (service/core/files.py and the line sinks): never opened through a symlink,
created 0644 whatever the umask, existing files keep their mode, and a refused reopen on
SIGHUP is logged and counted while the old file stays in use."""

from __future__ import annotations

import contextlib
import logging
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.core.errors import InputError
from service.core.files import OUTPUT_MODE, open_output
from service.output.sinks.lines import JsonlSink, LineSink


@contextlib.contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


@pytest.mark.parametrize("append", [False, True])
def test_a_symlink_to_a_file_is_refused_and_its_target_untouched(tmp_path, append):
    target = tmp_path / "precious"
    target.write_text("keep me\n")
    link = tmp_path / "out.jsonl"
    link.symlink_to(target)
    with pytest.raises(InputError, match=r"out\.jsonl: is a symlink"):
        open_output(link, append=append)
    assert target.read_text() == "keep me\n"


def test_a_dangling_symlink_is_refused_and_nothing_created(tmp_path):
    link = tmp_path / "out.nmea"
    link.symlink_to(tmp_path / "would-be-created")
    with pytest.raises(InputError, match="is a symlink"):
        open_output(link)
    assert not (tmp_path / "would-be-created").exists()


@pytest.mark.parametrize("mask", [0o000, 0o077, 0o277])
def test_new_files_are_0644_whatever_the_umask(tmp_path, mask):
    with umask(mask):
        for append in (False, True):
            p = tmp_path / f"new-{append}"
            with open_output(p, append=append) as fh:
                fh.write("x\n")
            assert _mode(p) == OUTPUT_MODE == 0o644


def test_an_existing_file_keeps_its_mode_truncated_or_appended(tmp_path):
    p = tmp_path / "out.csv"
    p.write_text("old\n")
    p.chmod(0o600)
    with umask(0), open_output(p, append=True) as fh:
        fh.write("more\n")
    assert p.read_text() == "old\nmore\n" and _mode(p) == 0o600
    with umask(0), open_output(p) as fh:
        fh.write("new\n")
    assert p.read_text() == "new\n" and _mode(p) == 0o600


def test_devices_are_still_outputs(tmp_path):
    with open_output("/dev/null") as fh:
        fh.write("nothing\n")
    assert _mode(Path("/dev/null")) == 0o666  # not touched


def test_line_sinks_refuse_symlinks_and_create_0644(tmp_path):
    target = tmp_path / "target"
    target.write_text("keep\n")
    link = tmp_path / "fixes.jsonl"
    link.symlink_to(target)
    for append in (False, True):
        with pytest.raises(InputError, match="is a symlink"):
            JsonlSink(str(link), append=append)
    assert target.read_text() == "keep\n"
    with umask(0):
        sink = JsonlSink(str(tmp_path / "new.jsonl"))
    sink.write_record("FIX", {"class": "FIX"})
    sink.close()
    assert _mode(tmp_path / "new.jsonl") == 0o644


def test_reopen_onto_a_planted_symlink_keeps_the_old_file(tmp_path, caplog):
    """logrotate renamed the file and someone planted a symlink at the path before SIGHUP:
    the sink logs, counts and keeps writing to the file it has."""
    path = tmp_path / "out.nmea"
    sink = LineSink(str(path), append=True)
    sink.write("one\n")
    rotated = tmp_path / "out.nmea.1"
    path.rename(rotated)
    target = tmp_path / "target"
    target.write_text("keep\n")
    path.symlink_to(target)
    with caplog.at_level(logging.ERROR, logger="service.output"):
        sink.reopen()
    sink.write("two\n")
    sink.close()
    assert sink.counters()["line_reopen_errors"] == 1
    assert any("is a symlink" in r.getMessage() for r in caplog.records)
    assert rotated.read_text() == "one\ntwo\n" and target.read_text() == "keep\n"
