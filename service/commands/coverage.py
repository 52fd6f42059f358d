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

    cfg = CoverageConfig(
        days=args.days,
        step_s=args.step_s,
        grid_deg=args.grid_deg,
        altitudes_m=tuple(args.altitudes_m),
        beta=args.beta,
        elmask_deg=args.elmask_deg,
    )
    check_output_path(args.json_out, "--json")
    check_plot(args.plot)
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
