"""u-blox RXM-SFRBX (BDS B1I D1/D2, GPS L1 C/A LNAV) to :class:`~service.core.types.NavSubframe`.

u-blox (F9 HPG Interface Description, UBX-RXM-SFRBX) delivers a BDS D1/D2 subframe as 10
dwords, one 30-bit word each in bits 29-0 (bits 31-30 are padding), in the ICD bit
numbering: de-interleaved, parity included, information bits first (BDS-SIS-ICD-B1I-3.0
5.1.3), so the words pass BCH(15,11,1) as delivered and word 1 opens with the preamble (the
tests check both on real captures).

u-blox sigId for gnssId 3: 0 B1I D1, 1 B1I D2, 2/3 B2I D1/D2, 4/10 B3I D1/D2 (others are
B1C/B2a, different messages). B2I and B3I carry the same D1/D2 format (the codec decodes
them, see the tests) but the service works on B1I, so only sigId 0 and 1 are mapped. The
message type follows the satellite (ICD 5.1: GEOs C01-C05/C59-C63 broadcast D2), which
also covers receivers that report sigId 0 for every BDS subframe.

GPS (gnssId 0) sigId 0, L1 C/A: the ten LNAV words as transmitted, one in bits 29-0 of each
dword, parity included (IS-GPS-200 20.3.5; :mod:`service.core.gps_nav` checks the parity,
and every word of the PolyU F9P capture passes). Other GPS signals (L2C CNAV, sigId 3/4)
are counted as unmapped.

Galileo (gnssId 2) sigId 1 (E1-B) and 5 (E5b-I), 8 dwords: one nominal I/NAV page, even
and odd part (Galileo OS SIS ICD 4.3.2.2; :func:`service.core.gal_nav.inav_word` checks the
part order, the page type and the CRC-24Q, and every page of the PolyU F9P capture passes);
its 128-bit word becomes an ``INAV`` :class:`NavSubframe` whose fields pygnssutils' RawNav
reads (:class:`service.core.gal_nav.InavAssembler`). F/NAV (E5a, sigId 3) and E6 pages are
counted as unmapped.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

from service.core.bds import nav_type as bds_nav_type
from service.core.bds_nav import b1i_subframe
from service.core.errors import DecodeError
from service.core.gal_nav import inav_subframe, inav_word
from service.core.gps_nav import lnav_subframe
from service.core.systems import GnssSystem, sat_id
from service.core.types import NavSubframe

log = logging.getLogger(__name__)

UBX_GNSS: dict[int, GnssSystem] = {
    0: GnssSystem.GPS,
    1: GnssSystem.SBAS,
    2: GnssSystem.GAL,
    3: GnssSystem.BDS,
    5: GnssSystem.QZS,
    6: GnssSystem.GLO,
    7: GnssSystem.IRN,
}
"""u-blox gnssId -> system (u-blox F9 HPG Interface Description, "GNSS identifiers"; 4 is
IMES, no satellite system). bdsfix reads BeiDou's (gnssId 3) and counts the others."""
B1I_SIGIDS = {0: "D1", 1: "D2"}
"""u-blox sigId -> the message type u-blox names for B1I."""
WORD_MASK = (1 << 30) - 1


def nav_subframe_from_sfrbx(msg: Any, gpst_week: int, gpst_tow_s: float) -> NavSubframe | None:
    """The subframe of a parsed RXM-SFRBX (pyubx2 or :func:`drivers.ubx.parse_rxm`): its
    fields to :func:`nav_subframe`."""
    return nav_subframe(
        int(msg.gnssId), int(msg.svId), int(msg.sigId), sfrbx_dwords(msg), gpst_week, gpst_tow_s
    )


def sfrbx_dwords(msg: Any) -> tuple[int, ...]:
    """The ``numWords`` data words of a parsed RXM-SFRBX, as delivered (padding included)."""
    blocks = getattr(msg, "blocks", None)  # drivers.ubx.parse_rxm: one dict per word
    if blocks is not None:
        return tuple(int(b["dwrd"]) for b in blocks)
    # pyubx2: dwrd_01 .. dwrd_NN
    return tuple(int(getattr(msg, f"dwrd_{i:02d}")) for i in range(1, int(msg.numWords) + 1))


def nav_subframe(
    gnss_id: int,
    sv_id: int,
    sig_id: int,
    dwords: tuple[int, ...],
    gpst_week: int,
    gpst_tow_s: float,
) -> NavSubframe | None:
    """The subframe of a RXM-SFRBX (its gnssId, svId, sigId and data words), time-tagged
    with the receive time (GPST): BDS B1I, GPS L1 C/A LNAV or Galileo I/NAV (module
    docstring).

    None for other GNSS or signals, a word count other than 10 (8 for Galileo), or a
    subframe that fails the preamble/header checks
    (:func:`service.core.bds_nav.parse_header`).
    """
    system = UBX_GNSS.get(gnss_id)
    if system is GnssSystem.GPS:
        return _gps_lnav(sv_id, sig_id, dwords, gpst_week, gpst_tow_s)
    if system is GnssSystem.GAL:
        return _gal_inav(sv_id, sig_id, dwords, gpst_week, gpst_tow_s)
    if system is not GnssSystem.BDS or len(dwords) != 10:
        return None
    sig_type = B1I_SIGIDS.get(sig_id)
    if sig_type is None:
        return None
    prn = sat_id(GnssSystem.BDS, sv_id)
    nav_type: Literal["D1", "D2"] = bds_nav_type(prn)
    if sig_type != nav_type:
        log.debug(
            "%s: sigId %d says %s, the satellite broadcasts %s", prn, sig_id, sig_type, nav_type
        )
    words = tuple(w & WORD_MASK for w in dwords)
    try:
        return b1i_subframe(prn, nav_type, words, gpst_week, gpst_tow_s)
    except DecodeError as exc:
        log.debug("%s SFRBX rejected: %s", prn, exc)
        return None


def _gps_lnav(
    sv_id: int, sig_id: int, dwords: tuple[int, ...], gpst_week: int, gpst_tow_s: float
) -> NavSubframe | None:
    """The LNAV subframe of a GPS L1 C/A SFRBX (sigId 0, 10 words), else None."""
    if sig_id != 0 or len(dwords) != 10:
        return None
    prn = sat_id(GnssSystem.GPS, sv_id)
    try:
        return lnav_subframe(prn, tuple(w & WORD_MASK for w in dwords), gpst_week, gpst_tow_s)
    except DecodeError as exc:
        log.debug("%s SFRBX rejected: %s", prn, exc)
        return None


GAL_INAV_SIGIDS = {1: "1B", 5: "7I"}
"""u-blox sigId -> RINEX signal of the Galileo I/NAV pages: E1-B and E5b-I."""


def _gal_inav(
    sv_id: int, sig_id: int, dwords: tuple[int, ...], gpst_week: int, gpst_tow_s: float
) -> NavSubframe | None:
    """The I/NAV word of a Galileo E1-B or E5b-I SFRBX (8 dwords), else None."""
    signal = GAL_INAV_SIGIDS.get(sig_id)
    if signal is None or len(dwords) != 8 or not 1 <= sv_id <= 36:
        return None
    prn = sat_id(GnssSystem.GAL, sv_id)
    try:
        word = inav_word(dwords)
    except DecodeError as exc:
        log.debug("%s SFRBX rejected: %s", prn, exc)
        return None
    return inav_subframe(prn, word, gpst_week, gpst_tow_s, signal)
