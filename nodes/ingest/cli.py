"""``constructaide bim summary MODEL... [--schedule FILE] [--at ISO] [--tz ZONE] [--json]``."""

from __future__ import annotations

import argparse
import json
import sys

from tqdm import tqdm

from constructaide.errors import UserError


def _advance(bar: tqdm, name: str) -> None:
    bar.set_postfix_str(name.rsplit("/", 1)[-1])
    bar.update(1)


def bim_summary_main(argv: list[str] | None = None) -> int:
    """Print element counts by class and storey, the schedule and element states at an instant."""
    from constructaide.bim.ifc import load_site_model
    from constructaide.bim.schedule import parse_time, zone
    from nodes.ingest.summary import format_summary, summarize

    p = argparse.ArgumentParser(prog="constructaide bim summary", description=bim_summary_main.__doc__)
    p.add_argument("models", nargs="+", help="IFC files forming one site model")
    p.add_argument("--schedule", help="MS Project XML, P6 XML/XER or CSV schedule")
    p.add_argument("--at", help="ISO date/time for element states (site-local unless it has an offset)")
    p.add_argument("--tz", default="UTC", help="site IANA time zone (default UTC)")
    p.add_argument("--drop-missing", action="store_true", help="drop schedule references to unknown elements")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    args = p.parse_args(argv)
    try:
        zi = zone(args.tz)
        at_ns = parse_time(args.at, zi, what="--at") if args.at else None
        bar = tqdm(total=len(args.models), desc="load IFC", unit="file", file=sys.stderr, disable=len(args.models) < 2)
        site = load_site_model(
            args.models,
            tz=args.tz,
            schedule_path=args.schedule,
            on_missing="drop" if args.drop_missing else "error",
            progress=lambda name: _advance(bar, name),
        )
        bar.close()
    except ValueError as exc:  # IfcLoadError, ScheduleError
        raise UserError(str(exc)) from None
    s = summarize(site, at_ns)
    print(json.dumps(s, indent=2, ensure_ascii=False) if args.json else format_summary(s))
    return 0
