"""u-blox RXM-SFRBX (BDS B1I) to :class:`~service.types.NavSubframe`.

u-blox delivers each BDS word in the low 30 bits of a 32-bit dword, deinterleaved, info bits
first and parity last (u-blox F9 Interface Description, RXM-SFRBX; checked on the PolyU F9P
capture, where every word of all 230 B1I subframes passes BCH(15,11)). sigId 0 is B1I D1,
sigId 1 B1I D2 (GEO); other BDS signals (B2I, B1C, ...) are not mapped.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

from service.bds_nav import parse_header
from service.errors import DecodeError
from service.types import NavSubframe

log = logging.getLogger(__name__)

GNSS_BDS = 3
B1I_SIGNALS: dict[int, Literal["D1", "D2"]] = {0: "D1", 1: "D2"}


def nav_subframe_from_sfrbx(msg: Any, gpst_week: int, gpst_tow_s: float) -> NavSubframe | None:
    """The subframe of a BDS B1I RXM-SFRBX, or None (other GNSS/signal, bad parity)."""
    if int(msg.gnssId) != GNSS_BDS or int(msg.numWords) != 10:
        return None
    nav_type = B1I_SIGNALS.get(int(msg.sigId))
    if nav_type is None:
        return None
    words = tuple(int(getattr(msg, f"dwrd_{i:02d}")) & 0x3FFFFFFF for i in range(1, 11))
    try:
        head = parse_header(words, nav_type)
    except DecodeError as exc:
        log.debug("C%02d SFRBX rejected: %s", int(msg.svId), exc)
        return None
    return NavSubframe(
        prn=f"C{int(msg.svId):02d}",
        nav_type=nav_type,
        fra_id=head.fra_id,
        sow_s=head.sow_s,
        words=words,
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        page=head.page,
        signal="2I",
    )
