"""Ephemeris store: entry checks, selection by toe, health and age, and an atomically
persisted copy.

Selection follows common receiver practice for BDS (ICD B1I 5.2.4.9: ephemerides are
referenced to t_oe and updated hourly): the healthy set whose t_oe is nearest to the
requested time, within ``max_age_s``. Every ephemeris, whatever its source (RINEX, decoded
D1/D2, RTCM 1042, the persisted store), enters through :meth:`EphemerisStore.add`, which
refuses a set that :func:`ephemeris_problem` finds fault with.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from numbers import Real
from pathlib import Path

import numpy as np

from service.core.constants import prn_number
from service.core.counters import Counters
from service.core.errors import EphemerisError
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.ratelog import RateLimitedLog
from service.core.timebase import diff_s
from service.core.types import Ephemeris, KlobucharParams

log = logging.getLogger(__name__)

STORE_VERSION = 1
ARRAYS_CACHE_SIZE = 256

SQRT_A_MIN_SQRT_M = 5000.0
SQRT_A_MAX_SQRT_M = 6700.0
"""Window for sqrt(A) [sqrt(m)]: a from 25,000 to 44,890 km. BDS MEOs have a = 27,906 km
(sqrt(A) 5282.6), IGSOs and GEOs a = 42,164 km (sqrt(A) 6493.4). The broadcast field
(ICD B1I 5.2.4.12: 32 bits unsigned, scale 2^-19) spans 0-8192, far wider."""
ECCENTRICITY_MAX = 0.1
"""Upper bound (exclusive) for e. BDS orbits are near circular (e of order 0.001-0.01);
the broadcast field (32 bits unsigned, scale 2^-33) spans 0-0.5."""
I0_MAX_RAD = math.radians(70.0)
"""Upper bound for i0 (lower bound 0). IGSOs and MEOs fly at about 55 deg, GEOs
below 10 deg."""
R_MIN_M = 25_000_000.0
R_MAX_M = 45_000_000.0
"""Window for the satellite's geocentric radius at t_oe [m]: MEO 27,906 km and IGSO/GEO
42,164 km, each within a * e (< 0.02) plus the C_rc/C_rs harmonics."""
URA_MAX_M = 6144.0
"""URAI 14 is URA <= 6144 m, URAI 15 is URA > 6144 m (ICD B1I 5.2.4.5): no bound at all,
so such a set is refused. 0.0 means "not stated" (RINEX writers, Table 1) and passes."""
LOG_INTERVAL_S = 60.0
"""A refusal log line per (PRN, check) at most this often (wall clock); the next says how
many refusals it stood for."""

_NUMERIC_FIELDS = tuple(
    f.name for f in dataclasses.fields(Ephemeris) if f.name not in ("prn", "source", "ura_m")
)


@dataclasses.dataclass(frozen=True, slots=True)
class EphemerisProblem:
    """Why an ephemeris is refused: ``check`` names the test (a counter key), ``detail``
    says what was found, for the log."""

    check: str
    detail: str

    def __str__(self) -> str:
        return self.detail


def _finite(value: object) -> bool:
    return isinstance(value, Real) and math.isfinite(value)


def ephemeris_problem(eph: Ephemeris) -> EphemerisProblem | None:
    """What is wrong with ``eph`` for positioning, or None when it is usable.

    Checks, in order, with the ``check`` names used as counter keys:

    - ``prn``: the ID is a BDS satellite (``Cnn``);
    - ``unhealthy``: SatH1 (ICD B1I 5.2.4.6) is not 0;
    - ``not_finite``: a numeric field is not a finite number;
    - ``ura``: URA is the unusable class URAI 15, > 6144 m, or not a number (5.2.4.5);
    - ``sqrt_a``, ``eccentricity``, ``inclination``: sqrt(A), e and i0 (ephemeris
      parameters, 5.2.4.12) within the BDS windows of this module's constants;
    - ``radius``: the position at t_oe by the user algorithm (5.2.4.12, Table 5-11,
      :func:`service.core.orbit.sat_pos_clock`) is finite and its radius within
      [R_MIN_M, R_MAX_M]; this also catches absurd harmonic corrections.

    Computed with numpy warnings silenced, so a bad set never prints a RuntimeWarning.
    """
    try:
        number = prn_number(eph.prn)
    except (ValueError, TypeError, IndexError):
        number = 0
    if not (isinstance(eph.prn, str) and eph.prn.startswith("C") and 1 <= number <= 63):
        return EphemerisProblem("prn", f"PRN {eph.prn!r} is not a BDS satellite ID")
    if _finite(eph.health) and eph.health != 0:
        return EphemerisProblem("unhealthy", f"unhealthy (SatH1={eph.health})")
    for name in _NUMERIC_FIELDS:
        value = getattr(eph, name)
        if not _finite(value):
            return EphemerisProblem("not_finite", f"{name} is {value!r}, not a finite number")
    ura_m = eph.ura_m
    if not (isinstance(ura_m, Real) and 0.0 <= ura_m <= URA_MAX_M):
        return EphemerisProblem(
            "ura", f"URA {ura_m!r} m: no usable accuracy (URAI 15 is > {URA_MAX_M:g} m)"
        )
    if not SQRT_A_MIN_SQRT_M <= eph.sqrt_a_sqrt_m <= SQRT_A_MAX_SQRT_M:
        return EphemerisProblem(
            "sqrt_a",
            f"sqrtA {eph.sqrt_a_sqrt_m:g} sqrt(m) outside "
            f"[{SQRT_A_MIN_SQRT_M:g}, {SQRT_A_MAX_SQRT_M:g}]",
        )
    if not 0.0 <= eph.e < ECCENTRICITY_MAX:
        return EphemerisProblem("eccentricity", f"e {eph.e:g} outside [0, {ECCENTRICITY_MAX:g})")
    if not 0.0 <= eph.i0_rad <= I0_MAX_RAD:
        return EphemerisProblem(
            "inclination",
            f"i0 {math.degrees(eph.i0_rad):.2f} deg outside [0, {math.degrees(I0_MAX_RAD):g}] deg",
        )
    with np.errstate(all="ignore"):
        pos_m, _ = sat_pos_clock(
            EphemerisArrays.from_ephemerides([eph]), eph.week, np.array([eph.toe_sow_s])
        )
        r_m = float(np.linalg.norm(pos_m[0]))
    if not R_MIN_M <= r_m <= R_MAX_M:  # also NaN
        return EphemerisProblem(
            "radius",
            f"radius at toe {r_m / 1e3:.0f} km outside "
            f"[{R_MIN_M / 1e3:.0f}, {R_MAX_M / 1e3:.0f}] km",
        )
    return None


class EphemerisStore:
    """Ephemerides per PRN plus the latest broadcast ionosphere coefficients."""

    def __init__(
        self, max_age_s: float = 7200.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.max_age_s = max_age_s
        self._by_prn: dict[str, dict[tuple[int, float], Ephemeris]] = {}
        self.iono: KlobucharParams | None = None
        self.refused = 0
        self.refused_by_reason = Counters()
        """Refusals per :class:`EphemerisProblem` check name."""
        self.last_refusal: EphemerisProblem | None = None
        """Why the latest refused set was refused."""
        self._refusal_log = RateLimitedLog(log, LOG_INTERVAL_S, clock)  # per (PRN, check)
        # column form of recently used ephemeris sets (the same set serves many epochs);
        # keyed by object identity, the entry holds the objects so identities stay unique
        self._arrays: dict[tuple[int, ...], tuple[tuple[Ephemeris, ...], EphemerisArrays]] = {}

    def __len__(self) -> int:
        return sum(len(v) for v in self._by_prn.values())

    @property
    def prns(self) -> list[str]:
        return sorted(self._by_prn)

    def add(self, eph: Ephemeris) -> bool:
        """Hold ``eph`` unless :func:`ephemeris_problem` refuses it; returns whether it was
        kept. A refused set is counted (``refused``, ``refused_by_reason``) and logged, and
        never replaces a set already held."""
        problem = ephemeris_problem(eph)
        if problem is not None:
            self.refused += 1
            self.refused_by_reason[problem.check] += 1
            self.last_refusal = problem
            self._log_refusal(eph, problem)
            return False
        self._by_prn.setdefault(eph.prn, {})[(eph.week, eph.toe_sow_s)] = eph
        return True

    def _log_refusal(self, eph: Ephemeris, problem: EphemerisProblem) -> None:
        """One line per (PRN, check) per LOG_INTERVAL_S: WARNING, or INFO for SatH1 != 0
        (a satellite flagged unhealthy is normal operation, not damaged data)."""
        self._refusal_log.log(
            logging.INFO if problem.check == "unhealthy" else logging.WARNING,
            (str(eph.prn), problem.check),
            "refused ephemeris %s week %s toe %s from %s: %s",
            eph.prn,
            eph.week,
            eph.toe_sow_s,
            eph.source,
            problem,
        )

    def arrays(self, ephs: Sequence[Ephemeris]) -> EphemerisArrays:
        """``EphemerisArrays.from_ephemerides(ephs)``, memoised for repeated sets."""
        key = tuple(map(id, ephs))
        hit = self._arrays.get(key)
        if hit is not None:
            return hit[1]
        if len(self._arrays) >= ARRAYS_CACHE_SIZE:
            self._arrays.clear()
        arr = EphemerisArrays.from_ephemerides(ephs)
        self._arrays[key] = (tuple(ephs), arr)
        return arr

    def add_all(self, ephs: Iterable[Ephemeris]) -> int:
        return sum(self.add(e) for e in ephs)

    def select(self, prn: str, bdt_week: int, bdt_sow_s: float) -> Ephemeris | None:
        """Healthy ephemeris of ``prn`` with t_oe nearest the BDT time, or None if too old."""
        cands = self._by_prn.get(prn)
        if not cands:
            return None
        best = min(
            cands.values(), key=lambda e: abs(diff_s(bdt_week, bdt_sow_s, e.week, e.toe_sow_s))
        )
        if abs(diff_s(bdt_week, bdt_sow_s, best.week, best.toe_sow_s)) > self.max_age_s:
            return None
        return best

    def prune(self, bdt_week: int, bdt_sow_s: float, keep_s: float = 86400.0) -> int:
        """Drop ephemerides whose t_oe is more than ``keep_s`` before the given time."""
        dropped = 0
        for prn in list(self._by_prn):
            d = self._by_prn[prn]
            for key in [k for k in d if diff_s(bdt_week, bdt_sow_s, *k) > keep_s]:
                del d[key]
                dropped += 1
            if not d:
                del self._by_prn[prn]
        return dropped

    def all(self) -> list[Ephemeris]:
        return [e for prn in self.prns for e in self._by_prn[prn].values()]

    # --- persistence -------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the store atomically: temp file in the same directory, fsync, rename, fsync
        of the directory. A crash (even SIGKILL or power loss) leaves either the old or the
        new store, never a torn one; temp files a crash left behind are removed here."""
        path = Path(path)
        doc = {
            "version": STORE_VERSION,
            "ephemerides": [dataclasses.asdict(e) for e in self.all()],
            "iono": None if self.iono is None else dataclasses.asdict(self.iono),
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        for stale in path.parent.glob(f".{path.name}.*"):  # one writer: these are crash debris
            stale.unlink(missing_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                json.dump(doc, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path, max_age_s: float = 7200.0) -> EphemerisStore:
        """Read a store written by :meth:`save`; a damaged file raises EphemerisError.

        Each set goes through :meth:`add`, so one that fails the entry checks is refused
        and logged, and the rest are kept."""
        store = cls(max_age_s=max_age_s)
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8"))
            if doc.get("version") != STORE_VERSION:
                raise EphemerisError(f"{path}: unsupported store version {doc.get('version')!r}")
            for item in doc["ephemerides"]:
                store.add(Ephemeris(**{**item, "source": "store"}))
            if doc.get("iono"):
                io = doc["iono"]
                store.iono = KlobucharParams(
                    alpha=tuple(io["alpha"]), beta=tuple(io["beta"]), system=io["system"]
                )
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise EphemerisError(f"{path}: cannot read ephemeris store: {exc}") from exc
        return store
