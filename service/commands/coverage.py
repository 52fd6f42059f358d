"""``bdsfix coverage``: the paper's usability study (Table 3) from Table 1 or a nav file."""

from __future__ import annotations

import argparse
import json
import logging

import numpy as np

from service.commands.options import check_output_path, check_plot, parse_start
from service.core.bds import is_geo
from service.core.errors import ConfigError, InputError
from service.core.files import open_output
from service.studies.coverage import (
    CoverageConfig,
    coverage_document,
    nav_geo_positions,
    plot_coverage,
    run_coverage,
    table1_geo_positions,
)

log = logging.getLogger(__name__)


def main_coverage(args: argparse.Namespace) -> int:
    """``bdsfix coverage``: run the study, write JSON/plot, print a summary table."""
    from service.core.timebase import gpst_from_utc, gpst_to_bdt

    check_output_path(args.json_out, "--json")
    check_plot(args.plot)
    if args.first_fix:
        return main_first_fix(args)
    cfg = CoverageConfig(
        days=8.0 if args.days is None else args.days,
        step_s=300.0 if args.step_s is None else args.step_s,
        grid_deg=1.0 if args.grid_deg is None else args.grid_deg,
        altitudes_m=tuple(args.altitudes_m),
        beta=args.beta,
        elmask_deg=0.0 if args.elmask_deg is None else args.elmask_deg,
    )
    if cfg.days <= 0 or cfg.step_s <= 0 or cfg.grid_deg <= 0 or not cfg.altitudes_m:
        raise ConfigError("--days, --step-s and --grid-deg must be positive, with an altitude")
    t_s = np.arange(cfg.n_epochs) * cfg.step_s
    if args.nav:
        from drivers.rinex import read_nav

        nav = read_nav(args.nav)
        if args.start:
            start = gpst_to_bdt(*gpst_from_utc(parse_start(args.start)))
        else:
            geo_sets = [e for p, s in nav.ephemerides.items() if is_geo(p) for e in s]
            if not geo_sets:
                raise InputError(f"{args.nav}: no GEO ephemerides")
            first = min(geo_sets, key=lambda e: (e.week, e.toe_sow_s))
            start = (first.week, first.toe_sow_s)
            log.info("--nav: the study starts at the first GEO t_oe, BDT %d/%.0f", *start)
        prns, sats = nav_geo_positions(nav.ephemerides, start, t_s)
        log.info("--nav: GEOs %s", " ".join(prns))
    else:
        if args.start:
            from service.sim.constellation import table1

            offset = (parse_start(args.start) - table1().epoch_utc).total_seconds()
            if abs(offset) > 30 * 86400:
                log.warning("Table 1 propagated two-body %.0f days from its epoch", offset / 86400)
            t_s = t_s + offset
        sats = table1_geo_positions(t_s)
    res = run_coverage(cfg, sats, progress=False if args.no_progress else None)
    doc = coverage_document(res)
    if args.json_out:
        text = json.dumps(doc, indent=2)
        if args.json_out == "-":
            print(text)
        else:
            with open_output(args.json_out) as fh:  # never through a symlink
                fh.write(text + "\n")
    if args.json_out != "-":
        print(f"{'':>12} {'max %':>8} {'min %':>8} {'all %':>8}  >= 4-GEO area (first epoch)")
        for key, v in doc["altitudes"].items():
            a = v["area"]
            area = (
                f"{a['lon_min_deg']:.0f}..{a['lon_max_deg']:.0f} E, "
                f"{a['lat_min_deg']:.0f}..{a['lat_max_deg']:.0f} N"
                if a
                else "none"
            )
            print(
                f"{float(key) / 1e3:>9.0f} km {v['max_pct']:8.1f} {v['min_pct']:8.1f} "
                f"{v['all_pct']:8.1f}  {area}"
            )
        a = doc["all"]
        print(f"{'all':>12} {a['max_pct']:8.1f} {a['min_pct']:8.1f} {a['all_pct']:8.1f}")
    if args.plot:
        plot_coverage(res, args.plot, cfg.beta)
    return 0


def main_first_fix(args: argparse.Namespace) -> int:
    """``bdsfix coverage --first-fix``: the paper's method beside the coarse-time first fix
    (:mod:`service.studies.first_fix_coverage`)."""
    from service.core.timebase import bdt_to_gpst, gpst_from_utc
    from service.studies import first_fix_coverage as ff

    cfg = ff.FirstFixConfig(
        days=1.0 if args.days is None else args.days,
        step_s=600.0 if args.step_s is None else args.step_s,
        grid_deg=2.0 if args.grid_deg is None else args.grid_deg,
        beta=args.beta,
        elmask_deg=10.0 if args.elmask_deg is None else args.elmask_deg,
    )
    if cfg.days <= 0 or cfg.step_s <= 0 or cfg.grid_deg <= 0:
        raise ConfigError("--days, --step-s and --grid-deg must be positive")
    t_s = np.arange(cfg.n_epochs) * cfg.step_s
    sample = None
    if args.nav:
        from service.commands.solve import load_navigation

        # every set kept and each satellite's nearest one propagated by the ICD equations
        # (5.2.4.12) over the span: visibility above a 10 deg mask does not need more
        store, iono = load_navigation([args.nav], max_age_s=ff.PROPAGATE_MAX_S)
        if args.start:
            start = gpst_from_utc(parse_start(args.start))
        else:
            toes = sorted((e.week, e.toe_sow_s) for e in store.all() if e.prn.startswith("C"))
            mid = toes[len(toes) // 2]
            start = bdt_to_gpst(mid[0], mid[1] - cfg.days * 86400.0 / 2)
            log.info("--nav: the span is centred on the file's median BeiDou t_oe")
        prns, sats = ff.positions_from_store(store, start, t_s)
        if args.solve_grid_deg > 0:
            picks = np.linspace(0, len(t_s) - 1, max(1, args.solve_epochs)).round()
            sample = ff.solve_sample(
                store, iono, start, [float(t_s[int(i)]) for i in picks], args.solve_grid_deg
            )
    else:
        from service.sim.constellation import positions_ecef, table1

        const = table1()
        if args.start:
            t_s = t_s + (parse_start(args.start) - const.epoch_utc).total_seconds()
        prns, sats = const.prns, positions_ecef(const, t_s)
    res = ff.run_first_fix(cfg, prns, sats)
    doc = ff.first_fix_document(res)
    if sample is not None:
        doc["solve_sample"] = ff.sample_figures(sample, cfg.min_sats)
    if args.json_out:
        text = json.dumps(doc, indent=2)
        if args.json_out == "-":
            print(text)
        else:
            with open_output(args.json_out) as fh:
                fh.write(text + "\n")
    if args.json_out != "-":
        ff.print_table(doc)
        print(
            f"{len(prns)} satellites, mask {cfg.elmask_deg:g} deg, {doc['epochs']} epochs "
            f"{cfg.step_s:g} s apart, grid {cfg.grid_deg:g} deg"
        )
        if sample is not None:
            s = doc["solve_sample"]
            print(
                f"solve_coarse on {s['solves']} simulated first epochs: fixed "
                f"{s['fixed_area_pct']:.2f} % of the area ({s['fixed_where_condition_pct']:.2f} "
                f"% where >= {cfg.min_sats} satellites), wrong integers {s['wrong']}, "
                f"error p50 {s['error_p50_m']} m, max {s['error_max_m']} m"
            )
    if args.plot:
        ff.plot_first_fix(res, args.plot)
    return 0
