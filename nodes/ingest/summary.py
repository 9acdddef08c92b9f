"""Human/JSON summary of a site model: counts by class and storey, schedule range, states at an instant."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from typing import Any
from zoneinfo import ZoneInfo

from constructaide.bim.model import SiteModel


def _iso(ns: int, tz: ZoneInfo) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).astimezone(tz).isoformat(timespec="minutes")


def summarize(site: SiteModel, at_ns: int | None = None) -> dict[str, Any]:
    """Plain-data summary (JSON-able): elements by class/storey/material, tasks, date range,
    planned (and actual) state counts at ``at_ns``."""
    tz = ZoneInfo(site.tz)
    lo, hi = site.bbox_m()
    out: dict[str, Any] = {
        "files": list(site.source_files),
        "schemas": list(site.schemas),
        "elements": len(site.elements),
        "by_class": {k: len(v) for k, v in site.by_class.items()},
        "by_storey": {k: len(v) for k, v in site.by_storey.items()},
        "materials": len(site.by_material),
        "bbox_min_m": [round(float(x), 3) for x in lo],
        "bbox_max_m": [round(float(x), 3) for x in hi],
        "origin_offset_m": list(site.origin_offset_m),
        "crs": site.map_conversion.crs_name if site.map_conversion else "",
        "gps": [site.gps.lat_deg, site.gps.lon_deg] if site.gps else None,
        "warnings": list(site.warnings),
        "tasks": [
            {
                "task_id": t.task_id,
                "name": t.name,
                "start": _iso(t.planned_start_ns, tz),
                "finish": _iso(t.planned_finish_ns, tz),
                "elements": len(t.element_ids),
            }
            for t in site.tasks
        ],
    }
    if site.tasks:
        out["schedule_start"] = _iso(min(t.planned_start_ns for t in site.tasks), tz)
        out["schedule_finish"] = _iso(max(t.planned_finish_ns for t in site.tasks), tz)
        out["scheduled_elements"] = len(site.windows)
    if at_ns is not None:
        out["at"] = _iso(at_ns, tz)
        out["planned_states"] = dict(Counter(site.planned_states(at_ns).values()))
        actual = Counter(str(site.actual_state(g, at_ns)) for g in site.windows if site.windows[g].has_actuals)
        if actual:
            out["actual_states"] = dict(actual)
            out["status"] = dict(Counter(site.schedule_status(g, at_ns) for g in site.windows))
    return out


def format_summary(s: dict[str, Any], max_tasks: int = 40) -> str:
    """Text rendering of :func:`summarize`'s output."""
    lines = [f"files: {', '.join(s['files'])}  ({', '.join(s['schemas'])})"]
    lines.append(f"elements: {s['elements']}  bbox {s['bbox_min_m']} .. {s['bbox_max_m']} m")
    if any(s["origin_offset_m"]):
        lines.append(f"origin offset: {s['origin_offset_m']} m")
    if s["crs"]:
        lines.append(f"CRS: {s['crs']}")
    if s["gps"]:
        lines.append(f"site lat/lon: {s['gps'][0]:.6f}, {s['gps'][1]:.6f}")
    lines.append("by class:")
    lines += [f"  {k:<32} {v:>6}" for k, v in sorted(s["by_class"].items(), key=lambda kv: -kv[1])]
    lines.append("by storey:")
    lines += [f"  {k or '(none)':<32} {v:>6}" for k, v in s["by_storey"].items()]
    tasks = s["tasks"]
    lines.append(f"tasks: {len(tasks)}")
    if tasks:
        span = f"{s['schedule_start']} .. {s['schedule_finish']}"
        lines.append(f"schedule: {span} ({s['scheduled_elements']} elements scheduled)")
        for t in tasks[:max_tasks]:
            lines.append(f"  {t['start']} .. {t['finish']}  {t['name'][:40]:<40} {t['elements']:>5} el")
        if len(tasks) > max_tasks:
            lines.append(f"  ... {len(tasks) - max_tasks} more")
    if "at" in s:
        lines.append(f"states at {s['at']}: " + ", ".join(f"{k} {v}" for k, v in sorted(s["planned_states"].items())))
        if "actual_states" in s:
            lines.append("actual: " + ", ".join(f"{k} {v}" for k, v in sorted(s["actual_states"].items())))
            lines.append("status: " + ", ".join(f"{k} {v}" for k, v in sorted(s["status"].items())))
    for w in s["warnings"][:10]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)
