"""``bdsfix solve`` and ``ttff`` read an Android GnssLogger log through the file registry."""

from __future__ import annotations

import contextlib
import io
import json
import os

import pytest

from service.commands.cli import main
from tests.engine.test_android_periods import PERTH
from tests.support.fixes import without_since_start

LOG = PERTH / "SensorLog20171005.txt"
NAV = PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx"


def test_solve_of_the_perth_log_gives_the_streams_fixes(tmp_path, capsys):
    """With the phone's own states (``--fractional none``) and every system (the command's
    default), the batch solver publishes the FIX records of the stream (``bdsfix replay``
    of the same log), byte for byte bar the stream's ``since_start_s``: all 445 epochs
    fixed, the first 12 by the coarse-time fix (every range fractional, the phone's time
    uncertain by 5.97 s: the prior 5 sigma of it, pipeline.wide_time_prior), the same
    decision in both (pipeline.coarse_time_fix). Its integrity checks are the stream's, by
    the one rule (recovered.RecoveredLedger): the 6 recovered ranges whose satellite's full
    range comes later in the log and 9 relative integers of the coarse-time fixes (checked
    against the first full range of their fix and system, 2 such anchors), none wrong."""
    out = tmp_path / "perth.jsonl"
    args = ["solve", str(LOG), str(NAV), "--fractional", "none", "--mode", "fast"]
    assert main([*args, "--format", "jsonl", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "445 epochs" in err and "fast solver coarse-time fixes 12 " in err
    assert "fast solver integrity checks 15 " in err and "failures 0" in err
    batch = out.read_text().splitlines()
    replayed = tmp_path / "replay.jsonl"
    args = ["replay", str(LOG), "--nav", str(NAV), "--max-speed", "--jsonl-out", str(replayed)]
    assert main(args) == 0
    assert "integrity checks 15, failures 0" in capsys.readouterr().err
    stream = [x for x in replayed.read_text().splitlines() if '"class":"FIX"' in x]
    assert len(batch) == len(stream) == 445
    assert [without_since_start(x) for x in stream] == batch
    records = [json.loads(x) for x in batch]
    assert all(r["mode"] != "none" for r in records)
    coarse = [k for k, r in enumerate(records) if r.get("method") == "coarse_time"]
    assert coarse == list(range(12))


def test_ttff_runs_emulated_restarts_on_the_perth_log(capsys):
    assert main(["ttff", str(LOG), str(NAV), "--trials", "5", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["conventional"]["success_pct"] > 0


def test_replay_takes_a_format_named_by_its_scheme(tmp_path, capsys):
    """``gnsslogger:PATH`` reaches the GnssLogger reader through replay's checks (the file
    exists, its day's nav) as a plain path does: the same 445 FIX records."""
    outs = []
    for spec in (str(LOG), f"gnsslogger:{LOG}"):
        out = tmp_path / f"{len(outs)}.jsonl"
        args = ["replay", spec, "--nav", str(NAV), "--max-speed", "--jsonl", str(out)]
        assert main(args) == 0
        outs.append([x for x in out.read_text().splitlines() if '"FIX"' in x])
    capsys.readouterr()
    assert len(outs[0]) == 445 and outs[0] == outs[1]


def _perth_copy(tmp_path, name: str, edit) -> str:
    """A copy of the Perth log's first 4000 lines (150 epochs) with ``edit(fields, k)``
    applied to the fields of its k-th Raw row (from 1), as ``gnsslogger:PATH``; the column
    numbers from the log's own header."""
    with LOG.open() as fh:
        head = [next(fh) for _ in range(4000)]
    names = next(x for x in head if x.startswith("# Raw,"))[2:].strip().split(",")
    col = {n: names.index(n) for n in ("TimeNanos", "BiasNanos", "FullBiasNanos")}
    out, k = [], 0
    for line in head:
        if line.startswith("Raw,"):
            k += 1
            f = line.rstrip("\n").split(",")
            lines = edit(f, k, col)
            out += [",".join(x) + "\n" for x in lines]
        else:
            out.append(line)
    path = tmp_path / f"{name}.txt"
    path.write_text("".join(out))
    return f"gnsslogger:{path}"


def _strict_json(line: str) -> dict:
    def refuse(word: str) -> None:
        raise ValueError(f"{word} in {line[:80]}")

    return json.loads(line, parse_constant=refuse)


def _set(name: str, value: str, rows=None):
    def edit(f, k, col):
        if rows is None or k in rows:
            f[col[name]] = value
        return [f]

    return edit


DAMAGES = {
    "clean": lambda f, k, col: [f],
    "every_row_twice": lambda f, k, col: [f, f],
    "bias_nan_mid": _set("BiasNanos", "NaN", set(range(1001, 1030))),
    "bias_nan": _set("BiasNanos", "NaN"),
    "bias_inf": _set("BiasNanos", "Infinity"),
    "full_bias_1e30": _set("FullBiasNanos", "-1e30"),
    "one_time_nanos": _set("TimeNanos", "-2123000000"),
}


@pytest.fixture(scope="module")
def damaged_runs(tmp_path_factory):
    """``bdsfix solve`` and ``bdsfix replay`` (every system) of each damaged copy: (exit
    codes, solve's records, replay's FIX records, stderr)."""
    tmp_path = tmp_path_factory.mktemp("damaged-perth")
    runs = {}
    for name, edit in DAMAGES.items():
        spec = _perth_copy(tmp_path, name, edit)
        solved, replayed = tmp_path / f"{name}.solve.jsonl", tmp_path / f"{name}.replay.jsonl"
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            rc_solve = main(["solve", spec, str(NAV), "--out", str(solved)])
            args = ["replay", spec, "--nav", str(NAV), "--max-speed", "--systems", "C,G,E"]
            rc_replay = main([*args, "--jsonl-out", str(replayed), "--nmea-out", os.devnull])
        fixes = [x for x in replayed.read_text().splitlines() if '"class":"FIX"' in x]
        runs[name] = (rc_solve, rc_replay, solved.read_text().splitlines(), fixes, err.getvalue())
    return runs


@pytest.mark.parametrize("name", [n for n in DAMAGES if n != "clean"])
def test_damaged_clock_fields_and_repeated_rows_never_crash_nor_change_the_fixes(
    damaged_runs, name
):
    """The reviewer's damaged phone logs (/tmp/rev-input/gl_*.txt, made again here): a
    BiasNanos NaN on Raw rows 1001-1029 once stopped ``solve`` after 75 records (NaN in the
    JSON) and ``replay`` with a traceback, NaN or Inf everywhere and a FullBiasNanos of
    -1e30 before any fix; every row twice gave 73 fast fixes instead of 132 and a replay
    with HPL 22 m for 53 m; one TimeNanos for every row ran past 120 s. Now both commands
    exit 0 with strict JSON: the repeated rows give exactly the clean copy's records, the
    mid-file NaN the clean records but those of its one epoch, the copies whose every epoch
    has no time none."""
    rc_solve, rc_replay, solved, fixes, err = damaged_runs[name]
    _, _, clean_solved, clean_fixes, clean_err = damaged_runs["clean"]
    assert "skipped input" not in clean_err
    assert (rc_solve, rc_replay) == (0, 0)
    records = [_strict_json(x) for x in solved]
    assert len(clean_solved) == 2 * 150 and len(clean_fixes) == 150  # both solvers
    if name == "every_row_twice":
        assert solved == clean_solved and fixes == clean_fixes
        # both summaries (solve's, then replay's) say what was dropped
        assert err.count("skipped input: android_duplicate_rows") == 2
    elif name == "bias_nan_mid":
        times = {r["gpst_tow_s"] for r in map(json.loads, clean_solved)}
        (lost,) = times - {r["gpst_tow_s"] for r in records}
        assert solved == [x for x in clean_solved if json.loads(x)["gpst_tow_s"] != lost]
        assert fixes == [x for x in clean_fixes if json.loads(x)["gpst_tow_s"] != round(lost, 6)]
    elif name == "one_time_nanos":
        assert len(records) <= 2 and len(fixes) <= 1  # one epoch
    else:
        assert records == [] and fixes == []


INTEGRITY = ("integrity_checks", "integrity_failures", "integrity_unchecked")


def _integrity(counters) -> dict[str, int]:
    return {k: int(counters.get(k, 0)) for k in (*INTEGRITY, "integrity_relative_anchors")}


@pytest.mark.parametrize(("restart_at", "checks", "unchecked"), [(None, 15, 0), (14, 13, 6)])
def test_a_receiver_restart_drops_pending_checks_in_solve_as_in_the_stream(
    tmp_path, restart_at, checks, unchecked
):
    """The Perth log, and a copy with HardwareClockDiscontinuityCount 1 from its 15th epoch
    on (the phone's clock restarted there: drivers.gnsslogger marks the epoch
    ``restarted``), through ``bdsfix solve``'s check (``--fractional none``) and the
    stream's Pipeline: by the one rule (recovered.RecoveredLedger) both check the same 15
    recovered ranges without the restart, and with it both drop the 6 still waiting for
    their satellite's full range (``integrity_unchecked``), checking 13; none wrong."""
    from drivers.source import file_epochs
    from service.commands.solve import BatchOptions, load_navigation, solve_epochs
    from service.core.counters import Counters
    from service.core.types import MeasurementEpoch
    from service.engine.pipeline import Pipeline

    path = LOG
    if restart_at is not None:
        lines = LOG.read_text().splitlines(keepends=True)
        names = next(x for x in lines if x.startswith("# Raw,"))[2:].strip().split(",")
        k, t = names.index("HardwareClockDiscontinuityCount"), names.index("TimeNanos")
        times = sorted({int(x.split(",")[t]) for x in lines if x.startswith("Raw,")})
        out = []
        for line in lines:
            f = line.split(",")
            if line.startswith("Raw,") and int(f[t]) >= times[restart_at]:
                f[k] = "1"
            out.append(",".join(f))
        path = tmp_path / "restarted.txt"
        path.write_text("".join(out))
    store, iono = load_navigation([str(NAV)], systems="CGE")
    events, _ = file_epochs(path, systems=("C", "G", "E"))
    epochs = [e for e in events if isinstance(e, MeasurementEpoch)]
    assert [k for k, e in enumerate(epochs) if e.restarted] == (
        [] if restart_at is None else [restart_at]
    )
    batch = Counters()
    opts = BatchOptions(mode="fast", fractional="none")
    assert len(list(solve_epochs(iter(epochs), store, iono, opts, batch))) == 445
    pipe = Pipeline(store, iono)
    for epoch in epochs:
        pipe.on_epoch(epoch)
    assert _integrity(batch) == _integrity(pipe.counters)
    assert [batch[k] for k in INTEGRITY] == [checks, 0, unchecked]
    # the summaries say it: "unchecked N" only where some went unchecked
    said = f"failures 0, unchecked {unchecked}" if unchecked else "failures 0\n"
    for args in (
        ["solve", str(path), str(NAV), "--mode", "fast", "--fractional", "none"],
        ["replay", str(path), "--nav", str(NAV), "--max-speed", "--jsonl-out", os.devnull],
    ):
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            assert main([*args, "--out", os.devnull] if args[0] == "solve" else args) == 0
        line = next(x for x in err.getvalue().splitlines(True) if "integrity checks" in x)
        assert f"integrity checks {checks}" in line and said in line, line
