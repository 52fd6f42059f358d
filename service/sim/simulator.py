"""Virtual receiver: a real UBX byte stream with true D1/D2 subframe timing (BeiDou) and,
with ``SimConfig.systems``, GPS LNAV subframe and Galileo I/NAV page timing.

For a true position, start time and receiver clock offset, each visible satellite is
acquired after a random delay (code lock: fractional measurement, T = 1 ms), reaches bit sync
after a further random delay, waits for the next preamble (the first subframe that starts
after sync) and becomes full once the SOW of that subframe has decoded, words 1-2: 0.12 s
into a D2 subframe (GEOs, 500 bps, 0.6 s subframes), 1.2 s into a D1 subframe (IGSO/MEO,
50 bps, 6 s subframes) (BDS-SIS-ICD-B1I-3.0 5.1.3, 5.2.2-5.2.3, 5.3.1-5.3.2; the SOW-decode
rule of :mod:`service.core.sow_rule`; ``full_rule="subframe"`` waits for the end of that
subframe instead). Subframe boundaries are those of the real signal: multiples of 0.6 s /
6 s of BDT transmit time, received one flight time later.

Per epoch the stream carries RXM-SFRBX for every subframe completed since the last epoch
(synced satellites only), RXM-MEASX with the code phase of every tracked satellite, and
RXM-RAWX whose prMes is valid only for satellites that are full. Pseudoranges come from
:mod:`service.sim.rangegen` (light time, Sagnac, satellite clock with TGD1, Klobuchar,
Saastamoinen, Gaussian noise) and are quantised to the MEASX code-phase step (2^-21 ms), so
that the fractional value a decoder reads back is exactly the full one modulo the code
period (1 ms; 4 ms for Galileo E1).

GPS and Galileo satellites of the ephemerides given join when ``systems`` names them (issue
19): GPS LNAV subframes of 6 s on GPST with the HOW (IS-GPS-200 20.3.2, 20.3.3.2: full 1.2 s
into the first subframe after bit sync), Galileo E1-B I/NAV pages of 2 s on odd GST seconds
(OS SIS ICD 4.3.2.2, 4.3.5: full at the end of the first page of word type 0/5/6 after page
sync), RAWX gnssId 0 / 2 sigId 0, SFRBX LNAV subframes and I/NAV pages; MEASX carries the
systems of ``measx_systems`` (BeiDou alone by default, so that the built-in scenario and
the TTFF studies keep their figures; with ``"CGE"`` GPS and Galileo are fractional rows from
code lock, as from a real F9P). They draw from random streams of their own, so the
BeiDou satellites' draws, and a BeiDou-only stream, are the same whatever else is simulated.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.core.bds import is_geo, subframe_period_s
from service.core.bds_nav import D1_SUBFRAME_S, D2_SUBFRAME_S, encode_d1_subframes, encode_d2_frame
from service.core.constants import C_M_S, WEEK_S
from service.core.gal_nav import (
    E1B_FIRST_PAGE_S,
    E1B_SUBFRAME_WORDS,
    encode_page,
    next_tow_page_start_s,
)
from service.core.gal_nav import encode_word as encode_inav_word
from service.core.geometry import geodetic_to_ecef
from service.core.gps_nav import SUBFRAME_S as LNAV_SUBFRAME_S
from service.core.gps_nav import encode_subframe as encode_lnav
from service.core.gps_nav import subframe_words as lnav_words
from service.core.orbit import EphemerisArrays
from service.core.sow_rule import DEFAULT_FULL_RULE, INAV_PAGE_S, time_known_after_s
from service.core.systems import constants_of, prn_number, wavelength_m
from service.core.timebase import (
    BDT_GPST_OFFSET_S,
    GST_GPS_WEEK_OFFSET,
    diff_s,
    gpst_to_bdt,
    normalize,
)
from service.core.types import Ephemeris, KlobucharParams
from service.engine.tracker import message_of
from service.sim.rangegen import true_ranges
from service.sim.ubx import MeasxSv, RawxMeas, measx_frame, rawx_frame

log = logging.getLogger(__name__)

CODE_PHASE_LSB_MS = 2.0**-21
PR_LSB_M = C_M_S * 1e-3 * CODE_PHASE_LSB_MS
LEAP_S = 18
UBX_OUTPUTS = ("RXM-SFRBX", "RXM-MEASX", "RXM-RAWX")
_GNSS_ID = {"C": 3, "G": 0, "E": 2}
"""u-blox gnssId of each simulated system (F9 HPG Interface Description)."""
_SIMULATED = frozenset(_GNSS_ID)
"""The UBX messages of an epoch, in the order the virtual receiver sends them."""


@dataclass(frozen=True, slots=True)
class SimConfig:
    """Scenario of the virtual receiver (true values)."""

    lat_deg: float = 39.9
    lon_deg: float = 116.4
    alt_m: float = 50.0
    start_gpst_week: int = 2161
    start_gpst_tow_s: float = 4 * 86400 + 3 * 3600 + 36 * 60.0
    duration_s: float = 60.0
    rate_hz: float = 10.0
    clock_offset_s: float = 0.0123
    noise_m: float = 1.3
    doppler_noise_hz: float = 0.05  # carrier-loop noise of a static receiver, 1 cm/s on B1I
    seed: int = 0
    elmask_deg: float = 5.0
    acq_delay_s: tuple[float, float] = (0.02, 0.10)  # warm start: Doppler and code known
    d2_sync_delay_s: tuple[float, float] = (0.01, 0.04)  # 2 ms bits, no NH code
    d1_sync_delay_s: tuple[float, float] = (0.1, 0.5)  # 20 ms bits behind the NH code
    tropo: bool = True
    full_rule: str = DEFAULT_FULL_RULE  # when prMes becomes valid (service.core.sow_rule)
    systems: str = "C"  # RINEX letters of the systems simulated from the ephemerides given
    measx_systems: str = "C"  # those of them RXM-MEASX carries (a real F9P: every system)


@dataclass(slots=True)
class _SatState:
    prn: str
    acq_s: float  # receiver time since start when code locks
    sync_s: float  # when bit sync is reached
    full_s: float = math.inf  # when the time is known: SOW of the first subframe after sync
    next_subframe_k: int | None = None  # index of the next subframe to report


@dataclass(frozen=True, slots=True)
class SimSubframe:
    """A subframe completed by the virtual receiver (what RXM-SFRBX carries)."""

    prn: str
    nav_type: str
    index: int  # subframe (I/NAV: page) number since the week start of its system's time
    start_bdt_sow_s: float  # its start: BDT sow; GPST (LNAV) or GST (I/NAV) tow
    received_s: float  # receiver time since start


@dataclass(frozen=True, slots=True, eq=False)
class SimEpoch:
    """One epoch of the virtual receiver, with the truth kept beside it."""

    t_s: float  # true time since start
    tag_gpst_week: int
    tag_gpst_tow_s: float
    prn: tuple[str, ...]
    pr_m: np.ndarray  # full pseudoranges (quantised), whatever the receiver knows
    full: np.ndarray  # bool: prMes valid
    cn0_dbhz: np.ndarray
    doppler_hz: np.ndarray  # B1I Doppler, positive for an approaching satellite
    subframes: tuple[SimSubframe, ...] = ()
    truth_x_ecef_m: np.ndarray = field(default_factory=lambda: np.zeros(3))


class Simulator:
    """Generates :class:`SimEpoch` s and their UBX encoding for one scenario."""

    def __init__(
        self,
        ephemerides: Sequence[Ephemeris],
        cfg: SimConfig | None = None,
        iono: KlobucharParams | None = None,
        iono_gps: KlobucharParams | None = None,
    ) -> None:
        self.cfg = cfg or SimConfig()
        self.iono = iono
        self.iono_gps = iono_gps
        """GPSA/GPSB: the delay of GPS and Galileo rows when given (a receiver corrects those
        rows with them, as RTKLIB does), else ``iono`` for every row."""
        self.x_ecef_m = geodetic_to_ecef(
            math.radians(self.cfg.lat_deg), math.radians(self.cfg.lon_deg), self.cfg.alt_m
        )
        rng = np.random.default_rng(self.cfg.seed)
        self._rng = rng
        # the Doppler noise draws from its own stream, so the pseudoranges' stream (and every
        # simulated position) does not depend on whether Doppler is generated
        self._doppler_rng = np.random.default_rng([self.cfg.seed, 1])
        bw, bs = gpst_to_bdt(self.cfg.start_gpst_week, self.cfg.start_gpst_tow_s)
        # other systems draw from their own streams: the BeiDou satellites' draws (and so a
        # BeiDou-only stream) are the same whatever else is simulated
        self._other_rng = np.random.default_rng([self.cfg.seed, 2])
        self._other_doppler_rng = np.random.default_rng([self.cfg.seed, 3])
        wanted = set(self.cfg.systems.replace(",", "").upper()) | {"C"}
        chosen: dict[str, Ephemeris] = {}
        for e in ephemerides:
            if e.prn[0] not in wanted or e.prn[0] not in _SIMULATED:
                continue
            best = chosen.get(e.prn)
            if best is None or abs(diff_s(bw, bs, e.week, e.toe_sow_s)) < abs(
                diff_s(bw, bs, best.week, best.toe_sow_s)
            ):
                chosen[e.prn] = e
        ephs = [chosen[p] for p in sorted(chosen)]
        arr = EphemerisArrays.from_ephemerides(ephs)
        tr = true_ranges(arr, self.x_ecef_m, self.cfg.start_gpst_week, self.cfg.start_gpst_tow_s)
        vis = np.flatnonzero(tr.el_rad >= math.radians(self.cfg.elmask_deg))
        self.ephemerides = [ephs[i] for i in vis]
        self._arr = arr.take(vis)
        self._bds = np.array([p[0] == "C" for p in self._arr.prn], dtype=bool)
        self._wavelength_m = np.array([wavelength_m(p) for p in self._arr.prn])
        other_idx = np.flatnonzero(~self._bds)
        self._other_arr = self._arr.take(other_idx) if len(other_idx) else None
        self._sats = {}
        for group, g_rng in ((True, rng), (False, self._other_rng)):
            members = [e.prn for e in self.ephemerides if (e.prn[0] == "C") == group]
            for prn in members:
                self._sats[prn] = _SatState(
                    prn=prn, acq_s=float(g_rng.uniform(*self.cfg.acq_delay_s)), sync_s=0.0
                )
            for prn in members:
                st = self._sats[prn]
                # GPS: 20 ms bits (as D1); Galileo E1: page sync on its 250 sps symbols
                span = self.cfg.d2_sync_delay_s if is_geo(prn) else self.cfg.d1_sync_delay_s
                st.sync_s = st.acq_s + float(g_rng.uniform(*span))

    @property
    def prns(self) -> list[str]:
        return [e.prn for e in self.ephemerides]

    def epochs(self) -> Iterator[SimEpoch]:
        """Epochs at the configured rate, from the first one after start to the duration."""
        cfg = self.cfg
        n = round(cfg.duration_s * cfg.rate_hz)
        prev_t = 0.0
        for k in range(1, n + 1):
            t = k / cfg.rate_hz
            week, tow = normalize(cfg.start_gpst_week, cfg.start_gpst_tow_s + t)
            tr = true_ranges(
                self._arr,
                self.x_ecef_m,
                week,
                tow,
                cfg.clock_offset_s,
                iono=self.iono,
                tropo=cfg.tropo,
                noise_m=0.0,
            )
            pr_m, carrier_rate_m_s = tr.pr_m, tr.carrier_rate_m_s
            if self.iono_gps is not None and self._other_arr is not None:
                other = ~self._bds
                tr_o = true_ranges(
                    self._other_arr,
                    self.x_ecef_m,
                    week,
                    tow,
                    cfg.clock_offset_s,
                    iono=self.iono_gps,
                    tropo=cfg.tropo,
                    noise_m=0.0,
                )
                pr_m, carrier_rate_m_s = pr_m.copy(), carrier_rate_m_s.copy()
                pr_m[other], carrier_rate_m_s[other] = tr_o.pr_m, tr_o.carrier_rate_m_s
            if cfg.noise_m > 0:
                noise = np.empty(len(pr_m))
                noise[self._bds] = self._rng.normal(0.0, cfg.noise_m, int(self._bds.sum()))
                other = ~self._bds
                noise[other] = self._other_rng.normal(0.0, cfg.noise_m, int(other.sum()))
                pr_m = pr_m + noise
            pr_q = np.round(pr_m / PR_LSB_M) * PR_LSB_M
            flight_s = tr.geometric_m / C_M_S
            subframes: list[SimSubframe] = []
            tracked, full = [], []
            _, bdt_sow_rx = gpst_to_bdt(week, tow)
            for i, prn in enumerate(self._arr.prn):
                st = self._sats[prn]
                if t < st.acq_s:
                    continue
                tracked.append(i)
                subframes.extend(
                    self._completed_subframes(st, prev_t, t, bdt_sow_rx, float(flight_s[i]))
                )
                full.append(t >= st.full_s)
            prev_t = t
            idx = np.asarray(tracked, dtype=int)
            cn0 = 45.0 - 10.0 * (1.0 - np.sin(np.clip(tr.el_rad[idx], 0, None)))
            doppler = -carrier_rate_m_s[idx] / self._wavelength_m[idx]
            if cfg.doppler_noise_hz > 0:
                bds = self._bds[idx]
                dn = np.empty(len(idx))
                dn[bds] = self._doppler_rng.normal(0.0, cfg.doppler_noise_hz, int(bds.sum()))
                dn[~bds] = self._other_doppler_rng.normal(
                    0.0, cfg.doppler_noise_hz, int((~bds).sum())
                )
                doppler = doppler + dn
            yield SimEpoch(
                t_s=t,
                tag_gpst_week=tr.tag_gpst_week,
                tag_gpst_tow_s=tr.tag_gpst_tow_s,
                prn=tuple(self._arr.prn[i] for i in idx),
                pr_m=pr_q[idx],
                full=np.asarray(full, dtype=bool),
                cn0_dbhz=np.round(cn0),
                doppler_hz=doppler,
                subframes=tuple(sorted(subframes, key=lambda s: s.received_s)),
                truth_x_ecef_m=self.x_ecef_m,
            )

    def ubx_epochs(self) -> Iterator[tuple[SimEpoch, bytes]]:
        """Each epoch with its UBX bytes: SFRBX for completed subframes, MEASX, then RAWX."""
        for ep in self.epochs():
            yield ep, self.encode(ep)

    def encode(self, ep: SimEpoch, outputs: Collection[str] = UBX_OUTPUTS) -> bytes:
        """The UBX bytes of ``ep``: those of ``outputs`` among RXM-SFRBX (one per completed
        subframe), RXM-MEASX and RXM-RAWX, in that order."""
        parts = []
        if "RXM-SFRBX" in outputs:
            eph_of = {e.prn: e for e in self.ephemerides}
            parts = [
                _sfrbx(
                    sf.prn,
                    sf.nav_type,
                    subframe_words(eph_of[sf.prn], sf, self.iono, ep.tag_gpst_week),
                )
                for sf in ep.subframes
            ]
        if "RXM-MEASX" in outputs:
            keep = self.cfg.measx_systems
            parts.append(_measx(epoch_subset(ep, lambda p: p[0] in keep, ep.subframes)))
        if "RXM-RAWX" in outputs:
            parts.append(_rawx(ep, [is_geo(p) for p in ep.prn]))
        return b"".join(parts)

    def _completed_subframes(
        self, st: _SatState, t0: float, t1: float, bdt_sow_rx: float, flight_s: float
    ) -> list[SimSubframe]:
        """Subframes (I/NAV: pages) of ``st`` whose last bit arrived in (t0, t1] after sync.

        BeiDou D1/D2 subframes start on multiples of 6 s / 0.6 s of BDT, GPS LNAV subframes on
        multiples of 6 s of GPST (IS-GPS-200 20.3.2), Galileo E1-B pages on odd seconds of GST
        (= GPST; 2 s pages, OS SIS ICD 4.3.2.2). The time is known by the rule of
        :mod:`service.core.sow_rule` after the first subframe whose start follows sync; for
        Galileo at the end of the first page carrying a TOW (word types 0/5/6) that starts
        after sync (:func:`service.core.gal_nav.next_tow_page_start_s`)."""
        message = message_of(st.prn)
        if message in ("D1", "D2"):
            period, offset, t_sys_rx = subframe_period_s(st.prn), 0.0, bdt_sow_rx
        elif message == "LNAV":
            period, offset, t_sys_rx = LNAV_SUBFRAME_S, 0.0, bdt_sow_rx + BDT_GPST_OFFSET_S
        else:
            period, offset = INAV_PAGE_S, E1B_FIRST_PAGE_S
            t_sys_rx = bdt_sow_rx + BDT_GPST_OFFSET_S
        # receiver time since start <-> system transmit time: tx = t_sys_rx - (t1 - t) - flight
        tx_of = lambda t: t_sys_rx - (t1 - t) - flight_s  # noqa: E731
        if st.next_subframe_k is None:
            if t1 < st.sync_s:
                return []
            # the first preamble (page) after sync; the time is known once the rule says so
            k0 = math.ceil(round((tx_of(st.sync_s) - offset) / period, 9))
            st.next_subframe_k = k0
            if message == "INAV":
                known_tx = next_tow_page_start_s(k0 * period + offset) + INAV_PAGE_S
            else:
                known_tx = k0 * period + time_known_after_s(message, self.cfg.full_rule)
            st.full_s = t1 + (known_tx - tx_of(t1))
        out = []
        while True:
            k = st.next_subframe_k
            end_tx = (k + 1) * period + offset
            end_rx = t1 + (end_tx - tx_of(t1))
            if end_rx > t1 + 1e-9:
                break
            if end_rx > t0 - 1e-9:
                out.append(SimSubframe(st.prn, message, k, k * period + offset, end_rx))
            st.next_subframe_k = k + 1
        return out


def subframe_words(
    eph: Ephemeris, sf: SimSubframe, iono: KlobucharParams | None, gpst_week: int = 0
) -> list[int]:
    """The words of a completed subframe as RXM-SFRBX carries them: BeiDou's ten BCH-coded
    30-bit words in ICD order (5.1.3); GPS LNAV's ten parity-coded words (subframes 1-3 from
    the set, 4-5 empty; HOW = the next subframe's start, IS-GPS-200 20.3.3.2); a Galileo
    E1-B page's eight dwords (word type by :data:`service.core.gal_nav.E1B_SUBFRAME_WORDS`,
    TOW = the page's start). ``gpst_week`` is the week the subframe started in (LNAV's WN,
    I/NAV's WN)."""
    if sf.nav_type == "LNAV":
        sfid = sf.index % 5 + 1
        tow_next = round(sf.start_bdt_sow_s + LNAV_SUBFRAME_S)
        return lnav_words(encode_lnav(eph, sfid, tow_next, gpst_week))
    if sf.nav_type == "INAV":
        start = round(sf.start_bdt_sow_s)
        wtype = E1B_SUBFRAME_WORDS[int((start - E1B_FIRST_PAGE_S) % 30) // 2]
        gst_week = gpst_week - GST_GPS_WEEK_OFFSET
        return encode_page(encode_inav_word(eph, wtype, gst_week, start % int(WEEK_S)))
    frame, fra_id = divmod(sf.index, 5)
    if sf.nav_type == "D1":
        sow = round(frame * 5 * D1_SUBFRAME_S)
        return list(encode_d1_subframes(eph, sow, iono)[fra_id])
    sow = round(frame * 5 * D2_SUBFRAME_S)
    return list(encode_d2_frame(eph, sow, frame % 10 + 1, iono)[fra_id])


def _rawx(ep: SimEpoch, geo: Sequence[bool]) -> bytes:
    """RXM-RAWX: prMes valid only for full satellites (B1I sigId 0 = D1, 1 = D2)."""
    meas = [
        RawxMeas(
            pr_m=float(ep.pr_m[i]),
            gnss_id=_GNSS_ID[prn[0]],
            sv_id=prn_number(prn),
            sig_id=1 if geo[i] else 0,  # GPS L1 C/A and Galileo E1 C: sigId 0
            locktime_ms=1000,
            cn0_dbhz=int(ep.cn0_dbhz[i]),
            doppler_hz=float(ep.doppler_hz[i]),
            pr_std_index=5,
            pr_valid=bool(ep.full[i]),
        )
        for i, prn in enumerate(ep.prn)
    ]
    return rawx_frame(ep.tag_gpst_tow_s, ep.tag_gpst_week, LEAP_S, meas)


_CHIPS_PER_MS = {"C": 2046, "G": 1023, "E": 1023}
"""B1I 2.046 Mchip/s (BDS-SIS-ICD-B1I-3.0 3.2), GPS L1 C/A and Galileo E1 1.023 Mchip/s
(IS-GPS-200 3.3.2.3, Galileo OS SIS ICD 2.3.3)."""


def _measx(ep: SimEpoch) -> bytes:
    """RXM-MEASX: the code phase (pseudorange modulo the code period T: 1 ms, Galileo E1
    4 ms) of every satellite given, as the ZED-F9P writes it (:mod:`drivers.ubx`): the
    whole ms ``intCodePhase`` counted from the receiver's own ms epoch (the time tag), the
    chips of the signal's chip rate in ``wholeChips`` + ``fracChips``/1024."""
    gps_tow_ms = round(ep.tag_gpst_tow_s * 1000.0)
    svs = []
    for i, prn in enumerate(ep.prn):
        period_units = round(constants_of(prn).code_period_s * 1e3) << 21
        # code phase in 2^-21 ms, from the tag's ms epoch: mod(pr/c - tag_ms, T)
        units = (round(float(ep.pr_m[i]) / PR_LSB_M) - (gps_tow_ms << 21)) % period_units
        chips = units * _CHIPS_PER_MS[prn[0]]  # in 2^-21 chip
        svs.append(
            MeasxSv(
                gnss_id=_GNSS_ID[prn[0]],
                sv_id=prn_number(prn),
                cn0_dbhz=int(ep.cn0_dbhz[i]),
                whole_chips=chips >> 21,
                frac_chips=(chips >> 11) & 0x3FF,
                code_phase_units=units & ((1 << 21) - 1),
                int_code_phase_ms=units >> 21,
                doppler_hz=float(ep.doppler_hz[i]),
                wavelength_m=wavelength_m(prn),
            )
        )
    return measx_frame(
        gps_tow_ms, (gps_tow_ms - round(BDT_GPST_OFFSET_S * 1000)) % (WEEK_S * 1000), svs
    )


def _sfrbx(prn: str, nav_type: str, words: Sequence[int]) -> bytes:
    from pyubx2 import GET, UBXMessage

    kw: dict[str, Any] = {
        "gnssId": _GNSS_ID[prn[0]],
        "svId": prn_number(prn),
        "sigId": 1 if nav_type in ("D2", "INAV") else 0,  # Galileo I/NAV on E1-B: sigId 1
        "numWords": len(words),
        "chn": 0,
        "version": 2,
    }
    kw |= {f"dwrd_{i:02d}": int(w) for i, w in enumerate(words, start=1)}
    return bytes(UBXMessage("RXM", "RXM-SFRBX", GET, **kw).serialize())


def epoch_subset(
    ep: SimEpoch, keep: Callable[[str], bool], subframes: Sequence[SimSubframe] | None = None
) -> SimEpoch:
    """``ep`` with only the satellites ``keep`` accepts (a receiver not tracking the others),
    carrying ``subframes`` (default: its own) of those satellites."""
    mask = np.asarray([keep(p) for p in ep.prn], dtype=bool)
    return replace(
        ep,
        prn=tuple(p for p, k in zip(ep.prn, mask, strict=True) if k),
        pr_m=ep.pr_m[mask],
        full=ep.full[mask],
        cn0_dbhz=ep.cn0_dbhz[mask],
        doppler_hz=ep.doppler_hz[mask],
        subframes=tuple(
            sf for sf in (ep.subframes if subframes is None else subframes) if keep(sf.prn)
        ),
    )
