"""Replay of damaged copies of real captures (issue 5, "Corrupted streams").

Damage, seeded, written to tmp_path only: random bit flips on 0.01 % or 0.5 % of the bytes, inserted
blocks of random bytes, false UBX headers claiming a 64 KiB payload (``B5 62 02 15 FF FF``)
in front of chosen frames, a tail cut in the middle of a frame, and RINEX observation files
with broken epoch lines or a cut tail. Each damaged file goes through
``bdsfix replay --jsonl-out ... --zmq ipc://...`` in a subprocess, binary captures through
stdin (tests/support/replay.py: the last STATUS is received without racing the exit).

Expected values come from the clean run and from where the damage physically landed, with
frame boundaries found by pyubx2's own stream reader, never by the code under test:

- exit 0, no traceback, the skipped input counted in the last ZeroMQ ``STATUS`` record and
  in the shutdown log line;
- damage between frames (false headers) or after them (cut tail) loses no fix at all;
- blocks inserted at random offsets lose at most the frames they land in, and the run keeps
  >= 80 % of the clean run's fixes;
- bit flips (one bit in a fixed-seed random 0.01 % or 0.5 % of the bytes): at 0.01 % the
  PolyU replay keeps >= 80 % of the clean fixes (84 % of its RAWX frames survive). At
  0.5 % a 1.4-2 kB UBX RXM-RAWX frame survives with probability 0.995^1778 = 1.3e-4 (an
  RTCM BDS MSM5 of 370 B with 0.16), so 80 % of the clean fixes cannot be reached by any
  receiver that checks checksums: there the framer must recover every frame the flips did
  not touch, and the replay keep >= 80 % of the fixes whose measurement frame is intact;
- RINEX: a broken epoch costs that epoch only, is logged with file:line and counted, and
  every other epoch gives exactly the clean fix.

A fix that survived is compared with the clean run's fix where one frame carries an epoch's
measurements (a UBX RXM-RAWX). The F9R capture is RTCM MSM7, one frame per system and epoch
(1075 GPS, 1095 Galileo, 1125 BeiDou, every system selected): damage that takes one of them
leaves a fix of the other systems (a different position), and damage to the epoch's last
MSM (DF393 = 0) closes the epoch only at the next one, after ephemerides that followed it.
There the reference is the replay of exactly the frames the damage left intact (as
pyubx2 splits the clean capture): the damaged run must give that run's fixes, no other.
"""

from __future__ import annotations

import functools
import io
import json
import random
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
from pyubx2 import UBXReader

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from tests.support.paths import DATA, ROOT
from tests.support.replay import replay_with_status

REPO = ROOT
POLYU = DATA / "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx"
POLYU_NAV = DATA / "hk-polyu-f9p-ubx-2024/hksc269h.24f"
F9R = DATA / "ublox-logs/ublox-zed-f9r.log"
HKSC = DATA / "hksc-2021/hksc1610.obs"
HKSC_NAV = DATA / "hksc-2021/hksc1610.nav"
FALSE_HEADER = b"\xb5\x62\x02\x15\xff\xff"  # UBX RXM-RAWX claiming 65535 payload bytes
SEED = 5


# --- frames located by the library ------------------------------------------------------------


@dataclass(frozen=True)
class LibFrame:
    offset: int
    raw: bytes
    kind: str  # UBX message name, "rtcm<number>" or "nmea"


@functools.cache
def library_frames(path: Path) -> tuple[LibFrame, ...]:
    """Frames of a clean capture as pyubx2's stream reader splits it, with their offsets."""
    data = path.read_bytes()
    out: list[LibFrame] = []
    pos = 0
    for raw, msg in UBXReader(io.BytesIO(data), protfilter=7, quitonerror=0):
        if raw is None:
            continue
        at = data.find(raw, pos)
        assert at >= 0
        if raw[:1] == b"\xb5":
            kind = str(msg.identity)
        elif raw[:1] == b"\xd3":
            kind = f"rtcm{(raw[3] << 4) | (raw[4] >> 4)}"
        else:
            kind = "nmea"
        out.append(LibFrame(at, bytes(raw), kind))
        pos = at + len(raw)
    return tuple(out)


def measurement_kind(frames: tuple[LibFrame, ...]) -> str:
    return "RXM-RAWX" if any(f.kind == "RXM-RAWX" for f in frames) else "rtcm1125"


# --- damage ----------------------------------------------------------------------------------


def flip_bits(data: bytes, fraction: float, seed: int) -> tuple[bytes, set[int]]:
    """One random bit flipped in ``fraction`` of the bytes (chosen without repetition)."""
    rng = random.Random(seed)
    buf = bytearray(data)
    hit = set(rng.sample(range(len(buf)), round(fraction * len(buf))))
    for i in hit:
        buf[i] ^= 1 << rng.randrange(8)
    return bytes(buf), hit


def insert_blocks(data: bytes, n: int, seed: int) -> tuple[bytes, list[int]]:
    """``n`` blocks of 1-600 random bytes at random offsets of the clean stream."""
    rng = random.Random(seed)
    at = sorted(rng.sample(range(1, len(data)), n))
    parts, prev = [], 0
    for p in at:
        parts += [data[prev:p], rng.randbytes(rng.randrange(1, 601))]
        prev = p
    return b"".join([*parts, data[prev:]]), at


def false_headers(data: bytes, frames: tuple[LibFrame, ...], n: int, seed: int) -> bytes:
    """A false 64 KiB UBX header right in front of ``n`` chosen measurement frames."""
    rng = random.Random(seed)
    kind = measurement_kind(frames)
    chosen = sorted(rng.sample([f.offset for f in frames if f.kind == kind], n))
    parts, prev = [], 0
    for p in chosen:
        parts += [data[prev:p], FALSE_HEADER]
        prev = p
    return b"".join([*parts, data[prev:]])


def cut_tail(data: bytes, frames: tuple[LibFrame, ...]) -> bytes:
    """The capture cut in the middle of the measurement frame at about 90 % of the file."""
    kind = measurement_kind(frames)
    f = next(f for f in frames if f.kind == kind and f.offset >= 0.9 * len(data))
    return data[: f.offset + len(f.raw) // 2]


# --- running bdsfix replay -------------------------------------------------------------------


@dataclass
class Run:
    rc: int
    stderr: str
    fixes: list[dict]
    status: dict | None


def replay(path: Path, extra: list[str], workdir: Path) -> Run:
    """The replay at full speed (RINEX: paced), its fixes from the JSONL it wrote and its
    last STATUS, received without racing its exit (tests/support/replay.py)."""
    out = workdir / f"{path.name}.jsonl"
    res = replay_with_status(path, *extra, "--jsonl-out", str(out))
    fixes = []
    if out.exists():
        for line in out.read_text().splitlines():
            rec = json.loads(line)
            if rec["class"] == "FIX" and rec["mode"] != "none":
                fixes.append(rec)
    return Run(res.rc, res.stderr, fixes, res.statuses[-1] if res.statuses else None)


CASES: dict[str, tuple[str, str]] = {
    # name: (capture, damage)
    "polyu-clean": ("polyu", "clean"),
    "polyu-flip": ("polyu", "flip"),
    "polyu-flip-1e-4": ("polyu", "flip-1e-4"),
    "polyu-garbage": ("polyu", "garbage"),
    "polyu-false64k": ("polyu", "false64k"),
    "polyu-cut": ("polyu", "cut"),
    "f9r-clean": ("f9r", "clean"),
    "f9r-flip": ("f9r", "flip"),
    "f9r-garbage": ("f9r", "garbage"),
    "f9r-false64k": ("f9r", "false64k"),
    "f9r-cut": ("f9r", "cut"),
    "hksc-clean": ("hksc", "clean"),
    "hksc-broken-epochs": ("hksc", "broken"),
    "hksc-cut": ("hksc", "cut"),
}
SOURCES = {"polyu": (POLYU, ["--nav", str(POLYU_NAV)]), "f9r": (F9R, []), "hksc": (HKSC, [])}
SOURCES["hksc"] = (HKSC, ["--nav", str(HKSC_NAV)])


def broken_rinex(text: str) -> tuple[str, list[int]]:
    """Five kinds of broken epoch line; returns the text and the 1-based broken line numbers."""
    lines = text.splitlines(keepends=True)
    epochs = [i for i, line in enumerate(lines) if line.startswith(">")]
    chosen = [epochs[k] for k in (20, 60, 100, 140, 180)]
    edits = [
        lambda s: s[:7] + "xx" + s[9:],  # month not a number
        lambda s: s[:32] + "99" + s[34:] if s[32:35].strip() else s,  # count too large
        lambda s: s[:31] + "9" + s[32:],  # event flag 9 does not exist
        lambda s: s[:20] + "\n",  # line cut inside the seconds
        lambda s: s[:13] + "25" + s[15:],  # hour 25
    ]
    for i, edit in zip(chosen, edits, strict=True):
        lines[i] = edit(lines[i])
    return "".join(lines), [i + 1 for i in chosen]


@dataclass
class Damaged:
    path: Path
    info: dict


def make_damaged(name: str, workdir: Path) -> Damaged:
    capture, damage = CASES[name]
    src = SOURCES[capture][0]
    if damage == "clean":
        return Damaged(src, {})
    out = workdir / f"{name}{src.suffix}"
    if capture == "hksc":
        text = src.read_text()
        if damage == "broken":
            text, broken = broken_rinex(text)
            out.write_text(text)
            return Damaged(out, {"broken_lines": broken})
        lines = text.splitlines(keepends=True)
        epochs = [i for i, line in enumerate(lines) if line.startswith(">")]
        cut = epochs[int(0.9 * len(epochs))] + 5  # inside an epoch's records
        out.write_text("".join(lines[:cut]) + lines[cut][:30])
        return Damaged(out, {"cut_epoch_line": epochs[int(0.9 * len(epochs))] + 1})
    data = src.read_bytes()
    frames = library_frames(src)
    info: dict = {"frames": frames}
    if damage.startswith("flip"):
        fraction = 1e-4 if damage == "flip-1e-4" else 0.005
        damaged, hit = flip_bits(data, fraction, SEED)
        info["hit"] = hit
    elif damage == "garbage":
        damaged, info["at"] = insert_blocks(data, 40 if capture == "polyu" else 10, SEED)
    elif damage == "false64k":
        damaged = false_headers(data, frames, 20 if capture == "polyu" else 8, SEED)
    else:
        damaged = cut_tail(data, frames)
        info["cut_at"] = len(damaged)
    out.write_bytes(damaged)
    return Damaged(out, info)


def intact(frame: LibFrame, info: dict) -> bool:
    """Whether the damage described by ``info`` left ``frame`` whole."""
    end = frame.offset + len(frame.raw)
    if "hit" in info:
        return not any(i in info["hit"] for i in range(frame.offset, end))
    if "at" in info:  # a block inserted before byte p splits the frames around p
        return not any(frame.offset < p < end for p in info["at"])
    if "cut_at" in info:
        return end <= info["cut_at"]
    return True


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Damaged, Run]]:
    workdir = tmp_path_factory.mktemp("damaged")

    def one(name: str) -> tuple[Damaged, Run]:
        d = make_damaged(name, workdir)
        sub = workdir / name
        sub.mkdir()
        return d, replay(d.path, SOURCES[CASES[name][0]][1], sub)

    with ThreadPoolExecutor(max_workers=2) as pool:  # two cores
        results = dict(zip(CASES, pool.map(one, CASES), strict=True))
    return results


MULTI_FRAME = ("f9r-garbage", "f9r-cut", "f9r-flip")
"""Damaged RTCM MSM cases whose reference is the replay of their intact frames."""


@pytest.fixture(scope="module")
def intact_runs(runs, tmp_path_factory) -> dict[str, Run]:
    """For :data:`MULTI_FRAME`: the replay of the clean capture's frames that the damage
    left intact, concatenated in their order."""
    workdir = tmp_path_factory.mktemp("intact")

    def one(name: str) -> Run:
        damaged, _ = runs[name]
        capture = CASES[name][0]
        frames: tuple[LibFrame, ...] = damaged.info["frames"]
        path = workdir / f"{name}-intact{SOURCES[capture][0].suffix}"
        path.write_bytes(b"".join(f.raw for f in frames if intact(f, damaged.info)))
        sub = workdir / name
        sub.mkdir()
        return replay(path, SOURCES[capture][1], sub)

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(zip(MULTI_FRAME, pool.map(one, MULTI_FRAME), strict=True))


def _key(fix: dict) -> tuple[int, float]:
    return fix["gpst_week"], round(fix["gpst_tow_s"], 3)


def _fix_table(run: Run) -> dict[tuple[int, float], dict]:
    return {_key(f): f for f in run.fixes if f["solver"] == "fast"}


def _report(name: str, run: Run, clean: Run) -> float:
    kept = len(run.fixes) / len(clean.fixes)
    counters = (run.status or {}).get("counters", {})
    skipped = {k: v for k, v in counters.items() if "skipped" in k or k.endswith("resyncs")}
    print(f"{name}: fixes {len(run.fixes)}/{len(clean.fixes)} = {kept:.1%}; {skipped}")
    return kept


@pytest.mark.parametrize("name", [n for n in CASES if not n.endswith("clean")])
def test_damaged_replay_exits_cleanly_and_counts_what_it_skipped(runs, name):
    _, run = runs[name]
    assert run.rc == 0, run.stderr[-2000:]
    assert "Traceback" not in run.stderr
    assert run.status is not None, "no STATUS received:\n" + run.stderr[-2000:]
    assert run.status["class"] == "STATUS"
    counters = run.status["counters"]
    skipped = {k: v for k, v in counters.items() if k.endswith(("_skipped", "resyncs")) and v}
    assert skipped, counters
    # the replay summary names the same counters with the same values, once
    lines = [x for x in run.stderr.splitlines() if "skipped input:" in x]
    assert len(lines) == 1, run.stderr[-2000:]
    named = dict(p.rsplit(" ", 1) for p in lines[0].split("skipped input: ", 1)[1].split(", "))
    for key, value in skipped.items():
        assert named.get(key.removeprefix("source_")) == str(value), (key, lines[0])


@pytest.mark.parametrize(
    "name",
    ["polyu-garbage", "polyu-false64k", "polyu-cut", "f9r-garbage", "f9r-false64k", "f9r-cut"],
)
def test_damaged_binary_replay_keeps_the_fixes(runs, intact_runs, name):
    capture = CASES[name][0]
    _, run = runs[name]
    clean = runs[f"{capture}-clean"][1]
    kept = _report(name, run, clean)
    assert kept >= 0.8
    clean_fix, got = _fix_table(clean), _fix_table(run)
    if name.endswith(("false64k", "cut")):
        # damage between frames or after the last fix loses nothing before it
        last = max(got) if name.endswith("cut") else max(clean_fix)
        assert [k for k in clean_fix if k <= last] == list(got)
    # every fix that survived is the clean run's fix (or, for an epoch of several frames,
    # the fix of the intact frames), not a fix from damaged data
    ref_fix = _fix_table(intact_runs[name]) if name in MULTI_FRAME else clean_fix
    assert set(got) == set(ref_fix) if name in MULTI_FRAME else set(got) <= set(ref_fix)
    for k, f in got.items():
        assert f["x_ecef_m"] == pytest.approx(ref_fix[k]["x_ecef_m"], abs=1e-3)


def _intact(frame: LibFrame, hit: set[int]) -> bool:
    return not any(i in hit for i in range(frame.offset, frame.offset + len(frame.raw)))


def test_bit_flips_at_0_01_percent_keep_80_percent_of_the_clean_fixes(runs):
    """0.01 % of the bytes with one bit flipped (seed 5): the PolyU replay keeps >= 80 % of
    the clean run's fixes, each of them the clean run's fix."""
    _, run = runs["polyu-flip-1e-4"]
    clean = runs["polyu-clean"][1]
    kept = _report("polyu-flip-1e-4", run, clean)
    assert kept >= 0.8
    clean_fix = _fix_table(clean)
    for k, f in _fix_table(run).items():
        assert f["x_ecef_m"] == pytest.approx(clean_fix[k]["x_ecef_m"], abs=1e-3)


@pytest.mark.parametrize("name", ["polyu-flip", "f9r-flip", "polyu-flip-1e-4"])
def test_bit_flips_lose_no_frame_that_survived_intact(runs, intact_runs, name):
    """0.5 % (and 0.01 %) of the bytes with one bit flipped: the framer recovers every frame
    the flips did not touch, at its offset, and the replay keeps >= 80 % of the clean fixes
    whose measurement frame is intact (at 0.5 % hardly any RAWX frame is: see the top)."""
    capture = CASES[name][0]
    damaged, run = runs[name]
    clean = runs[f"{capture}-clean"][1]
    _report(name, run, clean)
    frames: tuple[LibFrame, ...] = damaged.info["frames"]
    hit: set[int] = damaged.info["hit"]
    # 1) the framer recovers every frame the flips did not touch, at its offset
    framer = Framer(PROTOCOLS)
    data = damaged.path.read_bytes()
    found = {(f.offset, f.raw) for f in framer.feed(data) + framer.flush()}
    missing = [f for f in frames if _intact(f, hit) and (f.offset, f.raw) not in found]
    assert not missing
    # 2) the replay keeps >= 80 % of the clean fixes whose measurement frame is intact
    kind = measurement_kind(frames)
    meas = [f for f in frames if f.kind == kind]
    survived = sum(_intact(f, hit) for f in meas) / len(meas)
    expected = survived * len(clean.fixes)
    print(f"{name}: {kind} frames intact {survived:.1%}, fixes expected ~{expected:.1f}")
    assert len(run.fixes) >= 0.8 * expected - 1  # -1: one epoch of rounding on tiny counts
    clean_fix = _fix_table(clean)
    if name in MULTI_FRAME:  # exactly the fixes of the intact frames' replay
        ref_fix, got = _fix_table(intact_runs[name]), _fix_table(run)
        assert set(got) == set(ref_fix)
        for k, f in got.items():
            assert f["x_ecef_m"] == pytest.approx(ref_fix[k]["x_ecef_m"], abs=1e-3)
        return
    for k in _fix_table(run):
        assert k in clean_fix  # no fix at a time the clean run did not have


def test_rinex_broken_epoch_lines_are_skipped_logged_and_counted(runs):
    damaged, run = runs["hksc-broken-epochs"]
    clean = runs["hksc-clean"][1]
    kept = _report("hksc-broken-epochs", run, clean)
    broken = damaged.info["broken_lines"]
    assert kept >= 0.8
    assert len(run.fixes) == len(clean.fixes) - len(broken)
    counters = run.status["counters"]
    assert counters["source_epochs_skipped"] == len(broken)
    for lineno in broken:
        assert f"{damaged.path.name}:{lineno}:" in run.stderr
    clean_fix, got = _fix_table(clean), _fix_table(run)
    for k, f in got.items():
        assert f["x_ecef_m"] == pytest.approx(clean_fix[k]["x_ecef_m"], abs=1e-6)


def test_rinex_cut_tail_loses_only_the_cut_epoch(runs):
    damaged, run = runs["hksc-cut"]
    clean = runs["hksc-clean"][1]
    _report("hksc-cut", run, clean)
    assert run.status["counters"]["source_epochs_skipped"] == 1
    assert f"{damaged.path.name}:" in run.stderr and "file ends inside the epoch" in run.stderr
    clean_keys, got = list(_fix_table(clean)), list(_fix_table(run))
    assert got == clean_keys[: len(got)] and len(got) >= 0.8 * len(clean_keys)


def test_solve_keeps_its_error_on_a_broken_epoch(runs, tmp_path):
    damaged, _ = runs["hksc-broken-epochs"]
    proc = subprocess.run(
        [sys.executable, "-m", "service", "solve", str(damaged.path), str(HKSC_NAV)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert f"{damaged.path.name}:{damaged.info['broken_lines'][0]}:" in proc.stderr


# --- a valid frame right after garbage is never lost ----------------------------------------


def garbage_before_frames(
    frames: tuple[LibFrame, ...], data: bytes, seed: int
) -> tuple[bytes, int]:
    """Garbage in front of every 7th frame: random bytes, false 64 KiB UBX and 1023 B RTCM
    headers, an unfinished NMEA sentence, or the first part of another real frame (whose
    true header claims more bytes than follow)."""
    rng = random.Random(seed)
    kinds = [
        lambda: rng.randbytes(rng.randrange(1, 300)),
        lambda: FALSE_HEADER,
        lambda: b"\xb5\x62\x02\x15\x00\x10" + rng.randbytes(rng.randrange(0, 64)),  # 4 KiB
        lambda: b"\xd3\x03\xff" + rng.randbytes(rng.randrange(0, 64)),
        lambda: b"$GNGGA,0123," + bytes(rng.randrange(48, 58) for _ in range(20)),
        lambda: (lambda f: f.raw[: rng.randrange(6, len(f.raw))])(rng.choice(frames)),
    ]
    parts, prev, n = [], 0, 0
    for k, f in enumerate(frames):
        if k % 7 == 3:
            parts += [data[prev : f.offset], kinds[n % len(kinds)]()]
            prev = f.offset
            n += 1
    return b"".join([*parts, data[prev:]]), n


def _signature(ev: object) -> tuple:
    fields = ("prn", "gpst_week", "gpst_tow_s", "toe_sow_s", "sow_s", "fra_id", "alpha")
    sig = [type(ev).__name__]
    for name in fields:
        v = getattr(ev, name, None)
        sig.append(tuple(v) if hasattr(v, "__len__") and not isinstance(v, str) else v)
    for name in ("pr_m", "frac_pr_m", "words"):
        v = getattr(ev, name, None)
        if v is not None:
            sig.append(tuple(float(x) for x in v))
    return tuple(sig)


def _decode(data: bytes, chunk: int, max_ubx_payload: int) -> tuple[list[bytes], list[tuple]]:
    from drivers.source import StreamDecoder

    dec = StreamDecoder(max_payload={"ubx": max_ubx_payload})
    framer = Framer(PROTOCOLS, max_payload={"ubx": max_ubx_payload})
    raws: list[bytes] = []
    events: list = []
    for i in range(0, len(data), chunk):
        raws += [f.raw for f in framer.feed(data[i : i + chunk])]
        events += dec.feed(data[i : i + chunk])
    raws += [f.raw for f in framer.flush()]
    events += dec.flush()
    return raws, [_signature(e) for e in events]


@pytest.mark.parametrize("capture", [POLYU, F9R])
@pytest.mark.parametrize("max_ubx_payload", [8192, 65535])
def test_valid_frame_right_after_garbage_is_never_lost(capture, max_ubx_payload):
    frames = library_frames(capture)
    data = capture.read_bytes()
    damaged, n = garbage_before_frames(frames, data, SEED)
    assert n > 100
    lib = [f.raw for f in frames]
    clean_raws, clean_events = _decode(data, 4096, max_ubx_payload)
    raws, events = _decode(damaged, 1000, max_ubx_payload)
    assert clean_raws == lib  # the framer agrees with pyubx2 on the clean capture
    assert raws == lib  # and every frame survives the garbage in front of it
    assert events == clean_events and len(events) > 20
