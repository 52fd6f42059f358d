"""``bdsfix ttff``: emulated restarts on real data, or restarts of the virtual receiver
streamed into ``bdsfix run`` (``--simulate``)."""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivers.source import file_epochs
from service.commands.options import (
    check_plot,
    full_rule,
    parse_start,
    solver_config,
    systems_of,
)
from service.commands.solve import load_navigation
from service.core.bds_nav import quantise_ephemeris
from service.core.ephemeris import EphemerisStore
from service.core.errors import ConfigError
from service.core.sow_rule import FULL_RULES
from service.core.timebase import gpst_from_utc
from service.core.types import Ephemeris, KlobucharParams, MeasurementEpoch
from service.daemon.config import STORE_NAME
from service.engine.solver import IonoSet
from service.sim.keplerian import table1_ephemerides
from service.sim.scenario import default_start_gpst
from service.sim.simulator import SimConfig
from service.studies.ttff import Trial, plot_trials, run_trial, summarize
from service.studies.ttff_sim import (
    SimStream,
    SimTrial,
    analyse,
    plan_trials,
    run_daemon_on_pty,
    summarize_sim,
)


def main_ttff(args: argparse.Namespace) -> int:
    if args.trials < 1:
        raise ConfigError(f"--trials must be at least 1, got {args.trials}")
    check_plot(args.plot)
    rule = full_rule(args)
    if not args.simulate and (not args.obs or not args.nav):
        raise ConfigError("ttff needs OBS and NAV (or --simulate)")
    run = run_simulated if args.simulate else run_rinex
    doc, trials = run(args, rule)
    if args.compare_rules:  # the same restarts under the other rule
        other = next(r for r in FULL_RULES if r != rule)
        doc["compare"] = run(args, other)[0]
    _print(doc, args.json)
    if args.plot:
        plot_trials(trials, args.plot)
    return 0


def run_rinex(args: argparse.Namespace, rule: str) -> tuple[dict[str, Any], list[Trial]]:
    """Emulated restarts on RINEX OBS/NAV by ``rule``: the JSON document and the trials (the
    restart epochs and sync delays depend on ``--seed`` only, so both rules see the same)."""
    store, iono = load_navigation(list(args.nav))
    events, _ = file_epochs(args.obs)
    epochs = [e for e in events if isinstance(e, MeasurementEpoch)]
    if len(epochs) < 40:
        raise ConfigError(f"{args.obs}: {len(epochs)} epochs; ttff needs at least 40")
    cfg = solver_config(args)
    rng = np.random.default_rng(args.seed)
    last = len(epochs) - 30
    from tqdm import tqdm

    trials = [  # progress on a terminal only (disable=None), on stderr
        run_trial(epochs, int(rng.integers(0, last)), store, iono, cfg, rng, full_rule=rule)
        for _ in tqdm(range(args.trials), desc="ttff restarts", unit="trial", disable=None)
    ]
    doc = summarize(trials)
    doc["full_rule"] = rule
    return doc, trials


RULES = {
    "sow": "time known once the SOW of the first subframe after bit sync decodes: "
    "D2 0.12 s, D1 1.2 s into it",
    "subframe": "time known at the end of the first subframe after bit sync: D2 0.6 s, D1 6 s",
}
ROWS = {
    "fast": "fast fix (this method)",
    "conventional": "conventional SPP (4 full ranges)",
    "geo_only": "GEO-only SPP (4+ GEOs, no gate)",
}


def _mm(distance_m: float) -> str:
    """A fast-vs-SPP distance as it means something: below 0.1 mm it is floating-point noise
    whose digits depend on the machine's BLAS kernel, so it prints as a bound."""
    return "< 0.1 mm" if distance_m < 1e-4 else f"{distance_m * 1e3:.1f} mm"


def _print(doc: dict[str, Any], as_json: bool) -> None:
    """The TTFF table (times from the restart to the first fix, in data time), or JSON."""
    if as_json:
        print(json.dumps(doc))
        return

    def sec(v: dict[str, Any], key: str) -> str:
        return f"{v[key]:5.2f} s" if key in v else "    n/a"

    for d in (doc, doc.get("compare")):
        if d is None:
            continue
        print(f"{'full rule':>34}: {d['full_rule']} ({RULES[d['full_rule']]})")
        for key, label in ROWS.items():
            v = d[key]
            print(
                f"{label:>34}: median {sec(v, 'median_s')}, p95 {sec(v, 'p95_s')}, "
                f"success {v['success_pct']:.0f} %"
                + (f", median error {v['median_err_m']:.1f} m" if "median_err_m" in v else "")
                + (
                    f", max |fast - SPP| {_mm(v['max_diff_to_spp_m'])}"
                    if key == "fast" and "max_diff_to_spp_m" in v
                    else ""
                )
            )
        if d["fast"].get("first_by_coarse_time"):
            v = d["fast"]
            print(
                f"{'first fix by the coarse-time fix':>34}: {v['first_by_coarse_time']} trials"
                + (
                    f", max |coarse - SPP| with no full range "
                    f"{v['coarse_no_full_max_diff_to_spp_m'] * 1e3:.0f} mm"
                    if "coarse_no_full_max_diff_to_spp_m" in v
                    else ""
                )
            )
        if "conventional_over_fast" in d:
            print(f"{'conventional / fast (medians)':>34}: {d['conventional_over_fast']:.1f}")


def _navigation(
    nav: Sequence[str], systems: frozenset[str] = frozenset("C")
) -> tuple[list[Ephemeris], EphemerisStore, IonoSet, KlobucharParams | None]:
    if nav:
        store, iono = load_navigation(list(nav), systems=systems)
        klob = iono.bds
        if systems != frozenset("C"):  # GPS/Galileo rows: GPSA/GPSB, in the stream and here
            return store.all(), store, IonoSet(bds=klob, gps=iono.gps), klob
        return store.all(), store, IonoSet(bds=klob), klob

    ephs = table1_ephemerides(0.0)
    store = EphemerisStore()
    # held as a receiver holds them, decoded (every field on its ICD LSB): the daemon's own
    # decoded sets then replace them unchanged, and its fixes and the SPP references here
    # use the same sets
    store.add_all(quantise_ephemeris(e) for e in ephs)
    return ephs, store, IonoSet(), None


def _start_time(
    start_utc: str | None, from_nav: bool, ephs: Sequence[Ephemeris]
) -> tuple[int, float]:
    """``--start``, else the simulation's default start (:func:`default_start_gpst`)."""
    if start_utc:
        return gpst_from_utc(parse_start(start_utc))
    return default_start_gpst(ephs if from_nav else None)


def run_simulated(args: argparse.Namespace, rule: str) -> tuple[dict[str, Any], list[SimTrial]]:
    """Everything ``ttff --simulate`` does with the virtual receiver's prMes valid by
    ``rule``, returning the JSON document and the trials."""
    if not -90.0 <= args.lat_deg <= 90.0 or not -180.0 <= args.lon_deg <= 360.0:
        raise ConfigError(f"--lat-deg/--lon-deg out of range: {args.lat_deg}, {args.lon_deg}")
    if args.rate_hz <= 0 or args.trials < 1 or args.trial_s < 2.0:
        raise ConfigError("--rate-hz > 0, --trials >= 1 and --trial-s >= 2 are required")
    nav = [p for p in (args.obs, *(args.nav or ())) if p]  # NAV files only, when simulating
    systems = systems_of(args)
    ephs, store, iono, klob = _navigation(nav, systems)
    store.max_age_s = args.max_eph_age_s
    week, tow = _start_time(args.start, bool(nav), ephs)
    # the daemon applies the same ionosphere model as the simulator (none without a nav file)
    cfg = solver_config(args, **({} if klob else {"iono": "off"}))
    base = SimConfig(
        lat_deg=args.lat_deg,
        lon_deg=args.lon_deg,
        alt_m=args.alt_m,
        rate_hz=args.rate_hz,
        noise_m=args.noise_m,
        elmask_deg=min(5.0, cfg.elmask_deg),
        full_rule=rule,
        systems="".join(sorted(systems)),
    )
    plans = plan_trials(week, tow, args.trials, args.trial_s, args.seed)
    stream = SimStream(ephs, klob, base, plans, args.trial_s, args.max_eph_age_s, iono.gps)
    with tempfile.TemporaryDirectory(prefix="bdsfix-ttff-") as tmp:
        state = Path(tmp)
        if not nav:
            store.save(state / STORE_NAME)  # warm start: Table 1 ephemerides held
        records = run_daemon_on_pty(
            stream,
            state,
            state / "out.jsonl",
            cfg,
            nav=nav,
            max_eph_age_s=args.max_eph_age_s,
            coarse_fix=args.coarse_fix,
            systems=systems,
        )
    trials = analyse(stream, records, store, iono, cfg, args.noise_m)
    location = {"lat_deg": args.lat_deg, "lon_deg": args.lon_deg, "alt_m": args.alt_m}
    doc = summarize_sim(trials, location)
    doc["full_rule"] = base.full_rule
    doc["rate_hz"] = args.rate_hz
    doc["sigma_m"] = args.noise_m
    doc["stream_epochs"] = len(stream.epochs)
    doc["start_gpst"] = [week, round(tow, 3)]
    doc["coarse_fix"] = args.coarse_fix
    return doc, trials
