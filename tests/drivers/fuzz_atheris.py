"""atheris (libFuzzer) harnesses for every driver's byte parser.

Run one target: ``python tests/drivers/fuzz_atheris.py TARGET [libFuzzer flags] CORPUS_DIR``; an
empty CORPUS_DIR is first seeded with inputs cut from the real captures under
``../shared/data`` (``--seed-corpus TARGET DIR`` does only that). ``tests/drivers/test_atheris.py``
runs every target for a bounded number of executions and time.

What each target allows to escape (anything else is a crash that libFuzzer reports):

- ``framer``, ``decoder``: the input as a byte stream, fed in two chunks, then flushed
  (:class:`drivers.framing.Framer`, :class:`drivers.source.StreamDecoder`): nothing.
- ``ubx``: the input as class, id and payload of a UBX frame (UBX frame structure; length
  and Fletcher checksum added by pyubx2's helper), parsed by pyubx2 and mapped by
  :class:`drivers.ubx.UbxMapper`: :class:`~service.core.errors.DecodeError` from the mapper;
  through :class:`~drivers.source.StreamDecoder`: nothing.
- ``rtcm``: the input as an RTCM3 payload (RTCM 10403.3 section 4, CRC-24Q by pyrtcm's
  helper), parsed by pyrtcm and mapped by :class:`drivers.rtcm.RtcmMapper`: DecodeError;
  through StreamDecoder: nothing.
- ``sfrbx``: the input as ten 32-bit dwords of a BDS B1I subframe (BDS-SIS-ICD-B1I-3.0
  5.1.3 words, u-blox RXM-SFRBX layout): :func:`service.core.bds_nav.parse_header` DecodeError,
  :class:`service.core.bds_nav.EphemerisAssembler` and :func:`drivers.sfrbx.nav_subframe_from_sfrbx`
  nothing.
- ``rinex_obs``, ``rinex_nav``: the input as a RINEX 3 file (:mod:`drivers.rinex`):
  :class:`~service.core.errors.FramingError`; the lenient observation reader raises it only
  for the header.
- ``gnsslogger``: the input as an Android GnssLogger log (:mod:`drivers.gnsslogger`), read
  through the file registry's reader: nothing.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
from pathlib import Path

import atheris
import numpy  # noqa: F401  (imported before instrumentation: not instrumented)
import pyrtcm
import pyubx2
from pyrtcm.rtcmhelpers import calc_crc24q
from pyubx2.ubxhelpers import calc_checksum

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

with atheris.instrument_imports(include=["drivers", "service"]):
    from drivers.framing import Framer, WeekContext
    from drivers.gnsslogger import events as gnsslogger_events
    from drivers.protocols import PROTOCOLS
    from drivers.rinex import RinexObsReader, read_nav
    from drivers.rtcm import RtcmMapper
    from drivers.sfrbx import nav_subframe_from_sfrbx
    from drivers.source import StreamDecoder
    from drivers.ubx import UbxMapper
    from service.core.bds_nav import EphemerisAssembler, parse_header
    from service.core.errors import DecodeError, FramingError

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
CAPTURES = (
    DATA / "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx",
    DATA / "ublox-logs/ublox-zed-f9r.log",
    DATA / "ublox-logs/ublox-zed-f9p-sfrbx.log",
)
TMP = Path(os.environ.get("BDSFIX_FUZZ_TMP") or tempfile.gettempdir())
"""Where the RINEX targets write their input as a file (one file per target, rewritten)."""


def _library(reader: object, raw: bytes) -> object | None:
    try:
        return reader.parse(raw)  # type: ignore[attr-defined]
    except Exception:  # the library refused the frame: StreamDecoder counts that
        return None


def ubx_frame(body: bytes) -> bytes:
    head, payload = body[:2].ljust(2, b"\x00"), body[2:]
    inner = head + len(payload).to_bytes(2, "little") + payload
    return b"\xb5\x62" + inner + calc_checksum(inner)


def rtcm_frame(payload: bytes) -> bytes:
    payload = payload[:1023] or b"\x00"
    head = b"\xd3" + len(payload).to_bytes(2, "big")
    return head + payload + calc_crc24q(head + payload).to_bytes(3, "big")


def fuzz_framer(data: bytes) -> None:
    framer = Framer(PROTOCOLS, max_payload={"ubx": 65535})
    cut = data[0] * len(data) // 256 if data else 0
    framer.feed(data[:cut])
    framer.feed(data[cut:])
    framer.flush()
    assert framer.buffered == 0


def fuzz_decoder(data: bytes) -> None:
    dec = StreamDecoder(gps_week=2300 if data[:1] < b"\x80" else None)
    cut = data[0] * len(data) // 256 if data else 0
    dec.feed(data[:cut])
    dec.feed(data[cut:])
    dec.flush()


def fuzz_ubx(data: bytes) -> None:
    raw = ubx_frame(data)
    msg = _library(pyubx2.UBXReader, raw)
    if msg is not None:
        mapper = UbxMapper(week=WeekContext(2300))
        with contextlib.suppress(DecodeError):
            mapper.on_message(msg)
            mapper.flush()
    StreamDecoder().feed(raw + raw)


def fuzz_rtcm(data: bytes) -> None:
    raw = rtcm_frame(data)
    msg = _library(pyrtcm.RTCMReader, raw)
    if msg is not None:
        mapper = RtcmMapper(week=WeekContext(2300))
        with contextlib.suppress(DecodeError):
            mapper.on_message(msg)
            mapper.flush()
    StreamDecoder(gps_week=2300).feed(raw)


def fuzz_sfrbx(data: bytes) -> None:
    data = data[:40].ljust(40, b"\x00")
    words = [int.from_bytes(data[4 * i : 4 * i + 4], "little") for i in range(10)]
    for nav_type in ("D1", "D2"):
        with contextlib.suppress(DecodeError):
            parse_header([w & 0x3FFFFFFF for w in words], nav_type)
    asm = EphemerisAssembler()
    for k in range(3):  # the same words as D1 subframes 1-3 (FraID is in the words)
        asm.feed("C06", "D1", [w & 0x3FFFFFFF for w in words[k:] + words[:k]])
    asm.feed("C01", "D2", [w & 0x3FFFFFFF for w in words])
    sv = 1 + data[0] % 63
    payload = bytes([3, sv, data[1] % 2, 0, 10, 0, 2, 0]) + data
    msg = _library(pyubx2.UBXReader, ubx_frame(b"\x02\x13" + payload))
    if msg is not None:
        nav_subframe_from_sfrbx(msg, 2300, 100.0)


def _as_file(data: bytes, suffix: str) -> Path:
    path = TMP / f"bdsfix-atheris-{os.getpid()}{suffix}"
    path.write_bytes(data)
    return path


def fuzz_rinex_obs(data: bytes) -> None:
    path = _as_file(data, ".obs")
    with contextlib.suppress(FramingError):
        list(RinexObsReader(path))
    try:
        reader = RinexObsReader(path, lenient=True)
    except FramingError:  # a header error is the one thing a lenient reader raises
        return
    list(reader)


def fuzz_rinex_nav(data: bytes) -> None:
    with contextlib.suppress(FramingError):
        read_nav(_as_file(data, ".nav"))


def fuzz_gnsslogger(data: bytes) -> None:
    list(gnsslogger_events(_as_file(data, ".txt")))


TARGETS = {
    "framer": fuzz_framer,
    "decoder": fuzz_decoder,
    "ubx": fuzz_ubx,
    "rtcm": fuzz_rtcm,
    "sfrbx": fuzz_sfrbx,
    "rinex_obs": fuzz_rinex_obs,
    "rinex_nav": fuzz_rinex_nav,
    "gnsslogger": fuzz_gnsslogger,
}


# --- seed corpus from the real captures ------------------------------------------------------


def _frames() -> list[bytes]:
    out: list[bytes] = []
    for path in CAPTURES:
        stream = io.BytesIO(path.read_bytes()[:300_000])  # plenty of each kind, seeded fast
        out += [bytes(raw) for raw, _ in pyubx2.UBXReader(stream, protfilter=7, quitonerror=0)]
    return out


def seed_corpus(target: str, out: Path) -> int:
    """Write seed inputs for ``target`` into ``out``; returns their number."""
    out.mkdir(parents=True, exist_ok=True)
    seeds: list[bytes] = []
    if target in ("framer", "decoder"):
        for path in CAPTURES:
            data = path.read_bytes()
            step = max(1, len(data) // 6)
            seeds += [data[i : i + 800] for i in range(0, len(data), step)]
    elif target == "ubx":
        used = {b"\x02\x15", b"\x02\x14", b"\x02\x13", b"\x01\x20", b"\x01\x07"}
        seen: dict[bytes, int] = {}
        for raw in _frames():
            if raw[:1] == b"\xb5" and raw[2:4] in used and seen.get(raw[2:4], 0) < 4:
                seen[raw[2:4]] = seen.get(raw[2:4], 0) + 1
                seeds.append(raw[2:4] + raw[6:-2])
    elif target == "rtcm":
        count: dict[int, int] = {}
        for raw in _frames():
            if raw[:1] == b"\xd3":
                num = (raw[3] << 4) | (raw[4] >> 4)
                if count.get(num, 0) < 3:
                    count[num] = count.get(num, 0) + 1
                    seeds.append(raw[3:-3])
    elif target == "sfrbx":
        for raw in _frames():
            if raw[2:4] == b"\x02\x13" and raw[6] == 3 and len(seeds) < 20:
                seeds.append(raw[14:-2])
    elif target in ("rinex_obs", "rinex_nav"):
        src = DATA / (
            "hksc-2021/hksc1610.obs" if target == "rinex_obs" else "hksc-2021/hksc1610.nav"
        )
        lines = src.read_bytes().splitlines(keepends=True)
        end = next(i for i, line in enumerate(lines) if b"END OF HEADER" in line) + 1
        seeds += [b"".join(lines[: end + n]) for n in (0, 40, 120)]
    elif target == "gnsslogger":
        for src in (
            DATA / "android-perth-s8-2017/SensorLog20171005.txt",
            DATA / "android-beijing-mi8-2022/gnss_log_2022_09_28_22_01_27.txt",
        ):
            lines = src.read_bytes().splitlines(keepends=True)
            seeds += [b"".join(lines[:n]) for n in (20, 60)]
    for k, seed in enumerate(seeds):
        (out / f"seed-{k:03d}").write_bytes(seed)
    return len(seeds)


def main() -> None:
    if sys.argv[1] == "--seed-corpus":
        print(seed_corpus(sys.argv[2], Path(sys.argv[3])))
        return
    name = sys.argv.pop(1)
    corpus = [Path(a) for a in sys.argv[1:] if not a.startswith("-")]
    if corpus and corpus[0].is_dir() and not any(corpus[0].iterdir()):
        print(f"seeded {seed_corpus(name, corpus[0])} inputs", flush=True)
    atheris.Setup(sys.argv, TARGETS[name])
    atheris.Fuzz()


if __name__ == "__main__":
    main()
