"""Automatic progress from the photos, scored against the synthetic site's truth, beside "the schedule says".

    python bench/progress.py [--size small] [--seed 0] [--recording demo.mcap] [--no-write] [--set JSON]

Runs `constructaide demo --size SIZE --seed SEED --answer-anchor-requests` (the streaming pipeline; registrations,
masks and sparse points as the nodes published them), then `constructaide progress --recording` (the progress
node's engine) on the recording, and scores its `observations.csv` / `elements.csv`. Only this scoring reads
`truth/`. The baseline is what the site's schedule says (the same IFC tasks the system reads): an element stands
once its task's planned finish has passed, on time.

- built per (photo, element visible and unoccluded in truth): an element is in that population when, rendered
  alone at the photo's true camera (640 px wide), at least 40 of its pixels lie in front of the true depth (so
  occluders and built elements in front hide it, whether or not it stands) and that is at least half its
  footprint; truth = built at capture time; a prediction other than `built` counts as not built;
- finish date: detected finish minus true finish in working days (Mon-Fri 07:00-16:00 local, the site's working
  hours), for elements a fixed camera sees (in the population of a fixed-camera photo) finished between the first
  and last photo; a missing detection counts as wrong;
- deviation class at the last photo: late elements should be `behind` (or `not_built` if truly still absent),
  early ones `ahead`, the never-built one `not_built`, on-time ones `on_time`. The truth's classes are against
  each element's planned slot, which the site's IFC holds as a sub-task nested in its trade task (generator v10;
  before, the IFC held trade tasks only); the "(task)" rows score the classes against the trade task's window
  instead (late = finished after the trade task's planned finish, early = before its planned start), what a
  schedule without element slots can resolve. "Resolvable by the photos" is the share of each class for which
  some photo the element is visible in was taken while it deviated (absent after its planned finish, standing
  before its planned start; the element's slot for the truth classes, the trade task's for "(task)"): the ceiling
  of any reading of these photos. "Seen by no photo" counts the class's elements no photo shows (buried footings
  and basement walls): any reading can only say `unknown` of them, which the class counts wrong;
- evidence time per photo (the engine's `process`: decode, layers render, cues, fusion update), median, 1920x1080
  photos when the site has them.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import hashlib
import json
import math
import statistics
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path
from zoneinfo import ZoneInfo

import cv2
import msgspec
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import code_version, table, write_section  # noqa: E402
from pipeline import run_demo  # noqa: E402

from constructaide.bimgeom import glb_to_meshes  # noqa: E402
from constructaide.camera import project_points, scaled_intrinsics  # noqa: E402
from constructaide.schedule4d import element_windows, task_ancestors  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import element_states, load_cameras, load_depth, true_camera  # noqa: E402
from nodes.progress.batch import read_inputs  # noqa: E402
from nodes.progress.modelview import LayerRenderer  # noqa: E402

TZ = "Europe/Amsterdam"
POP_WIDTH = 640
MIN_PX = 40
WORK_START, WORK_HOURS = 7, 9


def site_photos(site: Path) -> dict[str, str]:
    """photo_id (as the ingest node computes it) -> path relative to photos/."""
    return {
        hashlib.sha256(p.read_bytes()).hexdigest()[:16]: str(p.relative_to(site / "photos"))
        for p in sorted((site / "photos").rglob("*.jpg"))
    }


def working_hours(t: dt.datetime) -> float:
    """Working hours since 2026-01-05 (a Monday) of an aware datetime: Mon-Fri, 07:00-16:00 local."""
    local = t.astimezone(ZoneInfo(TZ))
    days = int(np.busday_count(np.datetime64("2026-01-05"), np.datetime64(local.date())))
    if local.weekday() >= 5:
        return days * WORK_HOURS
    h = local.hour + local.minute / 60 + local.second / 3600
    return days * WORK_HOURS + float(np.clip(h - WORK_START, 0, WORK_HOURS))


def parse(s: str | None) -> dt.datetime | None:
    return dt.datetime.fromisoformat(s) if s else None


def _groups(boxes: list[tuple[int, int, int, int]]) -> list[list[int]]:
    """Greedy groups of indices whose screen boxes do not overlap (rendered together, they cannot hide each other)."""
    groups: list[tuple[list[int], list[tuple[int, int, int, int]]]] = []
    for i, b in enumerate(boxes):
        for members, bs in groups:
            if all(b[2] < o[0] or o[2] < b[0] or b[3] < o[1] or o[3] < b[1] for o in bs):
                members.append(i)
                bs.append(b)
                break
        else:
            groups.append(([i], [b]))
    return [g for g, _ in groups]


def truth_population(
    site: Path, rel: str, gids: list[str], meshes: dict, renderer: LayerRenderer, cams: dict
) -> set[str]:
    """Elements visible and unoccluded in truth at this photo (see the module docstring)."""
    intr, T = true_camera(site, rel, cams)
    h = round(intr.height_px * POP_WIDTH / intr.width_px)
    wi = scaled_intrinsics(intr, POP_WIDTH, h)
    depth = cv2.resize(load_depth(site, rel), (POP_WIDTH, h), interpolation=cv2.INTER_NEAREST)
    depth = np.where(depth > 0, depth, np.inf)
    cam_from_world = np.linalg.inv(T)
    boxes, idx = [], []
    for i, g in enumerate(gids, start=1):
        v = meshes.get(g)
        if v is None:
            continue
        lo, hi = v[0].min(0), v[0].max(0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        px, z = project_points(wi, cam_from_world, corners)
        if np.all(z <= 0):
            continue
        if np.any(z <= 0.05) or not np.all(np.isfinite(px)):
            box = (0, 0, POP_WIDTH, h)
        else:
            box = (int(px[:, 0].min()) - 2, int(px[:, 1].min()) - 2, int(px[:, 0].max()) + 2, int(px[:, 1].max()) + 2)
        if box[2] < 0 or box[3] < 0 or box[0] >= POP_WIDTH or box[1] >= h:
            continue
        boxes.append(box)
        idx.append(i)
    out: set[str] = set()
    none = np.zeros(len(gids) + 1, bool)
    for group in _groups(boxes):
        built = none.copy()
        built[[idx[k] for k in group]] = True
        lay = renderer.render(wi, T, built, none)
        ids = lay.ids_built
        front = ids > 0
        vis = front & (lay.depth_built_m <= depth + 0.05)
        n_all = np.bincount(ids[front].astype(np.int64), minlength=len(gids) + 1)
        n_vis = np.bincount(ids[vis].astype(np.int64), minlength=len(gids) + 1)
        for k in group:
            i = idx[k]
            if n_vis[i] >= MIN_PX and n_vis[i] >= 0.5 * n_all[i]:
                out.add(gids[i - 1])
    return out


def prf(pred: list[bool], truth: list[bool]) -> tuple[float, float, float]:
    p, t = np.asarray(pred), np.asarray(truth)
    tp = float(np.sum(p & t))
    prec = tp / max(float(p.sum()), 1.0)
    rec = tp / max(float(t.sum()), 1.0)
    return prec, rec, (2 * prec * rec / (prec + rec) if prec + rec else 0.0)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def score(site: Path, recording: Path, out: Path) -> dict:
    """All figures of one run: ours (observations.csv / elements.csv in ``out``) and the schedule baseline."""
    by_id = site_photos(site)
    cams = load_cameras(site)
    st = element_states(site)
    inputs = read_inputs(recording)
    assert inputs.model is not None
    gids = [e.global_id for e in inputs.model.elements]
    meshes = glb_to_meshes(inputs.model.geometry_glb)
    windows = element_windows(inputs.model.tasks)
    # Each element under its outermost summary task's window (the trade task; "(task)" classes below).
    anc, by_tid = task_ancestors(inputs.model.tasks), {t.task_id: t for t in inputs.model.tasks}
    trade_windows = element_windows(
        msgspec.structs.replace(by_tid[(t.task_id, *anc[t.task_id])[-1]], element_ids=t.element_ids)
        for t in inputs.model.tasks
        if t.element_ids
    )
    renderer = LayerRenderer()
    renderer.set_model(gids, meshes)
    obs = {(r["photo_id"], r["global_id"]): r for r in read_csv(out / "observations.csv")}
    els = {r["global_id"]: r for r in read_csv(out / "elements.csv")}
    summary = json.loads((out / "summary.json").read_text())
    times = sorted(c["capture_time_utc_ns"] for c in cams.values())
    t_first, t_last = times[0], times[-1]

    rows = defaultdict(lambda: {"ours": [], "sched": [], "truth": []})
    seen_by_fixed: set[str] = set()
    seen_at: dict[str, list[int]] = defaultdict(list)  # element -> capture times of the photos it is visible in
    for pid, rel in sorted(by_id.items(), key=lambda kv: cams[kv[1]]["capture_time_utc_ns"]):
        t = cams[rel]["capture_time_utc_ns"]
        group = "phone" if cams[rel]["camera_id"] is None else "fixed"
        built_truth = set(st["photos"][rel])
        for g in truth_population(site, rel, gids, meshes, renderer, cams):
            w = windows.get(g)
            sched = w is not None and w.build_finish_ns is not None and w.build_finish_ns <= t
            o = obs.get((pid, g))
            for k in (group, "all"):
                rows[k]["ours"].append(o is not None and o["state"] == "built")
                rows[k]["sched"].append(sched)
                rows[k]["truth"].append(g in built_truth)
            seen_at[g].append(t)
            if group == "fixed":
                seen_by_fixed.add(g)
    built = {k: (prf(v["ours"], v["truth"]), prf(v["sched"], v["truth"]), len(v["truth"])) for k, v in rows.items()}

    # finish dates
    errs_ours, errs_sched = [], []
    for g in sorted(seen_by_fixed):
        e = st["elements"][g]
        af = parse(e["actual_finish"])
        if af is None or not (t_first < af.timestamp() * 1e9 <= t_last):
            continue
        truth_h = working_hours(af)
        det = parse(els[g]["detected_finish"])
        errs_ours.append(np.inf if det is None else (working_hours(det) - truth_h) / WORK_HOURS)
        pf = parse(els[g]["planned_finish"])
        errs_sched.append(np.inf if pf is None else (working_hours(pf) - truth_h) / WORK_HOURS)

    # deviation classes at the last photo
    dev = defaultdict(lambda: [0, 0, 0, 0, 0])  # class -> [n, ours right, schedule right, resolvable, seen by none]
    for g, e in st["elements"].items():
        af = parse(e["actual_finish"])
        absent_at_end = af is None or af.timestamp() * 1e9 > t_last
        ours = els[g]["deviation"]
        w, tw = windows.get(g), trade_windows.get(g)
        ok = {
            "late": ("behind", "not_built") if absent_at_end else ("behind",),
            "early": ("ahead",),
            "never_built": ("not_built",),
            "on_time": ("on_time",),
        }[e["deviation"]]
        for cls, right, win in ((e["deviation"], ok, w), (_task_class(af, tw, t_last), None, tw)):
            if cls is None:
                continue
            if right is None:
                right = {
                    "late (task)": ("behind", "not_built") if absent_at_end else ("behind",),
                    "early (task)": ("ahead",),
                    "on time (task)": ("on_time",),
                    "not built (task)": ("not_built",),
                }[cls]
            d = dev[cls]
            d[0] += 1
            d[1] += ours in right
            d[2] += "on_time" in right
            d[3] += _resolvable(cls, af, win, seen_at.get(g, []))
            d[4] += g not in seen_at
    # our deviation flags at the last photo: how many are right (precision; the classes above are recall)
    flags = {"behind": [0, 0], "ahead": [0, 0], "not_built": [0, 0]}
    for g, e in st["elements"].items():
        f = els[g]["deviation"]
        if f in flags:
            af = parse(e["actual_finish"])
            absent_at_end = af is None or af.timestamp() * 1e9 > t_last
            truth = e["deviation"]
            flags[f][0] += 1
            flags[f][1] += {
                "behind": truth == "late",
                "ahead": truth == "early",
                "not_built": truth == "never_built" or (truth == "late" and absent_at_end),
            }[f]
    big = [
        ms
        for pid, ms in summary["evidence_ms_per_photo"].items()
        if pid in by_id and cams[by_id[pid]]["width"] >= 1920 and cams[by_id[pid]]["height"] >= 1080
    ]
    all_ms = list(summary["evidence_ms_per_photo"].values())
    return {
        "built": built,
        "finish": (errs_ours, errs_sched),
        "deviation": dict(dev),
        "flags": flags,
        "ms_1080p": statistics.median(big) if big else float("nan"),
        "ms_all": statistics.median(all_ms) if all_ms else float("nan"),
        "n_1080p": len(big),
        "photos_processed": summary["photos_processed"],
        "photos": len(by_id),
    }


def _resolvable(cls: str, af: dt.datetime | None, w, times: list[int]) -> bool:  # noqa: ANN001
    """Whether any photo the element is visible in (truth population) was taken while its deviation showed:
    absent after its task's planned finish (late, never built), standing before its task's planned start (early).
    Otherwise no photo saw it deviate and any task-level reading of the photos calls it on time. On time: always
    (nothing to see)."""
    if cls in ("on_time", "on time (task)"):
        return True
    if w is None or w.build_finish_ns is None:
        return False
    t_af = math.inf if af is None else af.timestamp() * 1e9
    if cls in ("late", "late (task)", "never_built", "not built (task)"):
        return any(w.build_finish_ns < t < t_af for t in times)
    start = w.build_start_ns if w.build_start_ns is not None else w.build_finish_ns
    return any(t_af < t < start for t in times)


def _task_class(af: dt.datetime | None, w, t_last: int) -> str | None:  # noqa: ANN001
    """Truth class against the element's own task window (what a task-level schedule can resolve)."""
    if w is None or w.build_finish_ns is None:
        return None
    start = w.build_start_ns if w.build_start_ns is not None else w.build_finish_ns
    if af is None or af.timestamp() * 1e9 > t_last:
        return "not built (task)" if t_last > w.build_finish_ns else None
    t = af.timestamp() * 1e9
    if t > w.build_finish_ns:
        return "late (task)"
    if t < start:
        return "early (task)"
    return "on time (task)"


def within(errs: list[float], days: float = 1.0) -> float:
    return float(np.mean(np.abs(np.asarray(errs)) <= days)) if errs else float("nan")


def report(res: dict, label: str) -> tuple[str, str]:
    b_rows = []
    for k in ("fixed", "phone", "all"):
        if k not in res["built"]:
            continue
        (po, ro, fo), (ps, rs, fs), n = res["built"][k]
        b_rows.append([f"{label} {k}", n, po, ro, fo, ps, rs, fs])
    eo, es = res["finish"]
    med = lambda e: float(np.median(np.abs(e))) if e else float("nan")  # noqa: E731
    f_rows = [[label, len(eo), within(eo), med(eo), within(es), med(es)]]
    d_rows = [
        [
            label,
            cls,
            n,
            right / n if n else float("nan"),
            sched / n if n else float("nan"),
            res_ / n if n else 0.0,
            *rest,
        ]
        for cls, (n, right, sched, res_, *rest) in sorted(res["deviation"].items())
    ]
    g_rows = [[label, f, n, right, right / n if n else float("nan")] for f, (n, right) in res["flags"].items()]
    t_rows = [[label, res["photos_processed"], res["photos"], res["n_1080p"], res["ms_1080p"], res["ms_all"]]]
    return "\n".join(map(str, (b_rows, f_rows, d_rows, g_rows, t_rows))), json.dumps(
        {"b": b_rows, "f": f_rows, "d": d_rows, "g": g_rows, "t": t_rows}, default=float
    )


def tables(all_rows: list[dict]) -> str:
    b = table(
        [
            "run / photos",
            "(photo, element) pairs",
            "precision",
            "recall",
            "F1",
            "schedule precision",
            "schedule recall",
            "schedule F1",
        ],
        [r for x in all_rows for r in x["b"]],
    )
    f = table(
        [
            "run",
            "elements (fixed camera sees, finished in period)",
            "ours within ±1 working day",
            "ours median abs error (working days)",
            "schedule within ±1 day",
            "schedule median abs error",
        ],
        [r for x in all_rows for r in x["f"]],
    )
    d = table(
        [
            "run",
            "truth class",
            "elements",
            "ours right",
            "schedule right",
            "resolvable by the photos",
            "seen by no photo",
        ],
        [r + [""] * (7 - len(r)) for x in all_rows for r in x["d"]],
    )
    g = table(
        ["run", "our flag", "elements flagged", "right", "share right"],
        [r for x in all_rows for r in x.get("g", [])],
    )
    t = table(
        [
            "run",
            "photos with evidence",
            "photos",
            "1920x1080 photos",
            "evidence ms/photo (1920x1080, median)",
            "evidence ms/photo (all, median)",
        ],
        [r for x in all_rows for r in x["t"]],
    )
    return (
        f"Built per (photo, element):\n\n{b}\n\nFinish dates:\n\n{f}\n\nDeviation at the last photo:\n\n{d}\n\n"
        f"Our deviation flags at the last photo (right = behind: truly late; ahead: truly early; not built: never "
        f"built or late and still absent):\n\n{g}\n\nEvidence step time:\n\n{t}\n"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--recording", type=Path, help="score this demo recording instead of running the demo")
    ap.add_argument("--cache", type=Path, default=ROOT / ".cache" / "synth")
    ap.add_argument("--keep", type=Path, help="keep the progress outputs (CSV) in this folder")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument(
        "--set",
        metavar="JSON",
        help="engine parameter overrides (`constructaide progress --set`): a variant, printed only (nothing stored)",
    )
    args = ap.parse_args(argv)
    site = ensure_site(args.size, args.seed, args.cache)
    label = f"{args.size} seed {args.seed}"
    with tempfile.TemporaryDirectory() as tmp:
        if args.recording is None:
            recording, secs = run_demo(args.size, args.seed, Path(tmp), answer=True)
            ran = f"`constructaide demo --size {args.size} --seed {args.seed} --answer-anchor-requests` ({secs:.0f} s)"
        else:
            recording, ran = args.recording, f"the recording `{args.recording.name}`"
        out = args.keep or Path(tmp) / "progress"
        cmd = [sys.executable, "-m", "constructaide.app.cli", "progress", "--recording", str(recording)]
        over = ["--set", args.set] if args.set else []
        subprocess.run([*cmd, "--out", str(out), "--quiet", *over], cwd=ROOT, check=True)
        res = score(site, recording, out)
    text, blob = report(res, label + (f", variant {args.set}" if args.set else ""))
    print(text)
    if args.set:
        return 0
    results = ROOT / ".cache" / "bench-progress.json"
    results.parent.mkdir(parents=True, exist_ok=True)
    store = json.loads(results.read_text()) if results.exists() else {}
    store[label] = {**json.loads(blob), "ran": f"{ran}, code {code_version()}"}
    results.write_text(json.dumps(store, indent=1))
    if not args.no_write:
        runs = [store[k] for k in sorted(store)]
        ran_all = "; ".join(f"{k}: {store[k]['ran']}" for k in sorted(store))
        body = f"""Synthetic sites ({ran_all}), then `constructaide progress --recording` on each recording (the
progress node's engine; registrations, masks and sparse points as the streaming pipeline published them, every
NeedsAnchor answered by the demo's simulated user). Scoring reads `truth/` only; the baseline in the same runs is
the schedule the system reads (since generator v10 the IFC holds each element's planned slot as a sub-task of its
trade task). See `bench/progress.py` for the definitions.

{tables(runs)}"""
        write_section("progress", body, command="python bench/progress.py --size SIZE --seed SEED (one run per row)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
