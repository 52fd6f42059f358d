"""Galileo I/NAV words (service.core.gal_nav): pages of u-blox RXM-SFRBX (PolyU F9P capture)
and Septentrio GALRawINAV (Leuven mosaic capture) to words, word types 1-5 to ephemerides,
word type 10 to the GGTO, word types 0/5/6 to the time of week (Galileo OS SIS ICD 4.3.5).

References, none from the code under test: the CRC-24Q every real page carries; the
receivers' own time tags (the page carrying a TOW arrives 2 s after it: the TOW is GST at
the page's start); the E1-B and E5b-I pages, two independent streams of the same words;
the Septentrio receiver's own decode of the same satellites (GALNav blocks, read by pysbf2).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyubx2 import UBXReader

from drivers.source import open_source
from service.core.ephemeris import EphemerisStore
from service.core.errors import DecodeError
from service.core.gal_nav import (
    E1B_TOW_PAGE_STARTS_S,
    InavAssembler,
    inav_word,
    next_tow_page_start_s,
    word_tow_s,
    word_type,
)
from service.core.types import Ephemeris, NavSubframe, TimeOffset
from service.engine.tracker import FrameSyncTracker, SubframeEmulator, message_of
from tests.support.paths import DATA

POLYU = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
LEUVEN = DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf"
POLYU_WEEK = 2333


@functools.cache
def _polyu_pages() -> tuple[tuple[int, int, list[int], float], ...]:
    """(sigId, svId, dwords, latest RAWX rcvTow) of each Galileo E1-B/E5b-I SFRBX."""
    out = []
    last = math.nan
    with open(POLYU, "rb") as fh:
        for _, msg in UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is None:
                continue
            if msg.identity == "RXM-RAWX":
                last = float(msg.rcvTow)
            elif msg.identity == "RXM-SFRBX" and msg.gnssId == 2 and msg.sigId in (1, 5):
                dwords = [int(getattr(msg, f"dwrd_{i:02d}")) for i in range(1, 9)]
                out.append((int(msg.sigId), int(msg.svId), dwords, last))
    return tuple(out)


def test_every_real_page_passes_its_crc_and_a_flipped_bit_fails_it():
    pages = _polyu_pages()
    assert len(pages) == 994  # 520 E1-B + 474 E5b-I
    for _, _, dwords, _ in pages:
        inav_word(dwords)
    _, _, dwords, _ = pages[0]
    for bit in range(0, 234):  # even part 0-119 (tail 114-119), odd part 128-247
        k = bit if bit < 120 else bit + 8
        flipped = list(dwords)
        flipped[k // 32] ^= 1 << (31 - k % 32)
        tail_or_ssp = 114 <= bit < 120 or bit >= 226  # not covered by the CRC (ICD Table 39)
        if tail_or_ssp:
            inav_word(flipped)
        else:
            with pytest.raises(DecodeError):
                inav_word(flipped)


def test_tow_is_gst_at_the_start_of_its_page():
    """Word types 0 (Time '10'), 5 and 6 carry a TOW; u-blox delivers each page with the
    measurement epoch 2 s after it: the page's start (ICD 4.3.5)."""
    seen = set()
    for _, _, dwords, rcv_tow in _polyu_pages():
        word = inav_word(dwords)
        tow = word_tow_s(word)
        if tow is None:
            assert word_type(word) not in (5, 6)
            continue
        seen.add(word_type(word))
        if not math.isnan(rcv_tow):  # (pages before the first RAWX)
            assert rcv_tow == tow + 2.0
    assert seen == {0, 5, 6}


def test_e1b_tow_pages_follow_the_schedule():
    """E1-B pages carrying a TOW start at 5, 17, 19, 25, 27 s of each 30 s sub-frame."""
    starts = {
        word_tow_s(w) % 30
        for sig, _, d, _ in _polyu_pages()
        if sig == 1 and word_tow_s(w := inav_word(d)) is not None
    }
    assert starts
    assert starts == set(E1B_TOW_PAGE_STARTS_S)
    assert next_tow_page_start_s(285905.5) == 285917.0  # 285900 + 17
    assert next_tow_page_start_s(285929.0) == 285935.0  # next sub-frame's 5


def _assemble(sig: int) -> list[Ephemeris | TimeOffset]:
    asm = InavAssembler()
    out: list[Ephemeris | TimeOffset] = []
    for s, sv, dwords, _ in _polyu_pages():
        if s == sig:
            out += asm.feed(f"E{sv:02d}", inav_word(dwords), POLYU_WEEK)
    return out


def test_e1b_and_e5b_pages_give_the_same_ephemerides_and_ggto():
    """Two independent page streams of the same satellites: 7 sets from E1-B, 6 from E5b-I,
    equal for the 6 satellites both give; each passes the store's entry checks (healthy,
    SISA 3.12 m); word type 10's GGTO is the same from both."""
    e1, e5 = _assemble(1), _assemble(5)
    sets1 = {e.prn: e for e in e1 if isinstance(e, Ephemeris)}
    sets5 = {e.prn: e for e in e5 if isinstance(e, Ephemeris)}
    assert len(sets1) == 7 and len(sets5) == 6 and set(sets5) <= set(sets1)
    for prn, e in sets5.items():
        assert sets1[prn] == e
    store = EphemerisStore()
    assert all(store.add(e) for e in sets1.values())
    assert {e.ura_m for e in sets1.values()} == {3.12}
    assert all(e.source == "subframes" and e.toe_sow_s % 60 == 46 for e in sets1.values())
    (g1,) = [g for g in e1 if isinstance(g, TimeOffset)]
    (g5,) = [g for g in e5 if isinstance(g, TimeOffset)]
    assert g1 == g5 and g1.week == POLYU_WEEK and abs(g1.a0_s) < 20e-9


def test_leuven_words_equal_the_receivers_own_galnav():
    """The 11 s Leuven capture's GALRawINAV pages (E1-B words 1, 3, 5 and E5b-I words 2, 4,
    6 of each satellite) complete 9 sets; every field equals the receiver's own GALNav
    block of that satellite (IODnav, orbit, clock, BGD, SISA, health)."""
    with open_source(str(LEUVEN), systems=frozenset("CGE")) as src:
        events = list(src)
    words = [e for e in events if isinstance(e, NavSubframe) and e.nav_type == "INAV"]
    assert len(words) == 114 and {w.signal for w in words} == {"1B", "7I"}
    asm = InavAssembler()
    sets = [x for w in words for x in asm.feed(w.prn, w.words[0], w.gpst_week)]
    galnav = {e.prn: e for e in events if isinstance(e, Ephemeris) and e.prn[0] == "E"}
    assert len(sets) == 9
    for e in sets:
        assert isinstance(e, Ephemeris)
        ref = galnav[e.prn]
        for f in dataclasses.fields(Ephemeris):
            if f.name in ("prn", "source"):
                continue
            a, b = getattr(e, f.name), getattr(ref, f.name)
            assert math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-15), (e.prn, f.name, a, b)
    assert all(w.gpst_tow_s == w.sow_s + 2.0 for w in words if w.sow_s >= 0)


def test_tracker_takes_the_time_from_tow_words_only():
    tracker = FrameSyncTracker()
    tow_page = NavSubframe("E05", "INAV", 5, 285917, (0,), POLYU_WEEK, 285919.0, signal="1B")
    other = NavSubframe("E05", "INAV", 3, -1, (0,), POLYU_WEEK, 285915.0, signal="1B")
    assert tracker.on_subframe(other) == []
    (ev,) = tracker.on_subframe(tow_page)
    assert (ev.event, ev.nav_type, ev.sow_s) == ("sow", "INAV", 285917.0)
    assert message_of("E05") == "INAV"


def test_restart_emulator_waits_for_the_next_tow_page():
    """After a restart at GST 285905.0 with 0.3 s page sync and 75 ms flight, a Galileo
    satellite's time is known at the end of the page starting at 285917 (word 0): 285919.075;
    a GPS one at the HOW of the subframe after 285905.3: 285906 + 1.2 s + flight."""
    emu = SubframeEmulator(POLYU_WEEK, 285905.0, {"E05": 0.3, "G10": 0.3})
    pr_m = 0.075 * 299_792_458.0
    week, tow = emu.full_at_tow_s("E05", pr_m)
    assert week == POLYU_WEEK and tow == pytest.approx(285919.075)
    assert emu.full_at_tow_s("G10", pr_m)[1] == pytest.approx(285906 + 1.2 + 0.075)


@settings(deadline=None, max_examples=200, derandomize=True)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["E01", "E05", "E36"]),
            st.sampled_from([0, 1, 2, 3, 4, 5, 6, 10, 16, 63]),
            st.integers(0, (1 << 122) - 1),
        ),
        max_size=30,
    )
)
def test_assembler_takes_any_words(items):
    """Any word content of any type: the assembler returns sets and offsets only (judging a
    set's values is the store's job)."""
    asm = InavAssembler()
    for prn, wtype, body in items:
        out = asm.feed(prn, wtype << 122 | body, POLYU_WEEK)
        assert all(isinstance(x, Ephemeris | TimeOffset) for x in out)
