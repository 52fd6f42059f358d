"""Ephemeris store: selection by toe, health and age, and an atomically persisted copy.

Selection follows common receiver practice for BDS (ICD B1I 5.2.4.9: ephemerides are
referenced to t_oe and updated hourly): the healthy set whose t_oe is nearest to the
requested time, within ``max_age_s``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

from service.errors import EphemerisError
from service.orbit import EphemerisArrays
from service.timebase import diff_s
from service.types import Ephemeris, KlobucharParams

log = logging.getLogger(__name__)

STORE_VERSION = 1
ARRAYS_CACHE_SIZE = 256


class EphemerisStore:
    """Ephemerides per PRN plus the latest broadcast ionosphere coefficients."""

    def __init__(self, max_age_s: float = 7200.0) -> None:
        self.max_age_s = max_age_s
        self._by_prn: dict[str, dict[tuple[int, float], Ephemeris]] = {}
        self.iono: KlobucharParams | None = None
        self.refused = 0
        # column form of recently used ephemeris sets (the same set serves many epochs);
        # keyed by object identity, the entry holds the objects so identities stay unique
        self._arrays: dict[tuple[int, ...], tuple[tuple[Ephemeris, ...], EphemerisArrays]] = {}

    def __len__(self) -> int:
        return sum(len(v) for v in self._by_prn.values())

    @property
    def prns(self) -> list[str]:
        return sorted(self._by_prn)

    def add(self, eph: Ephemeris) -> bool:
        """Hold ``eph`` unless it is unhealthy (SatH1 != 0); returns whether it was kept."""
        if eph.health != 0:
            self.refused += 1
            log.info(
                "refused unhealthy ephemeris %s toe %s (SatH1=%d, from %s)",
                eph.prn,
                eph.toe_sow_s,
                eph.health,
                eph.source,
            )
            return False
        self._by_prn.setdefault(eph.prn, {})[(eph.week, eph.toe_sow_s)] = eph
        return True

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
        """Read a store written by :meth:`save`; a damaged file raises EphemerisError."""
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
