"""Progress with a person reviewing the readings in the workbench: what a weekly look at each camera changes.

    python bench/progress_review.py --size SIZE --seed SEED --recording demo.mcap [--every-days 7] [--no-write]

The shipping progress engine (``nodes.progress.batch``: the same engine as ``constructaide progress`` and the
streaming node) reads every registered photo of a demo recording, in capture order, and keeps the PhotoEvidence each
photo gave (what the streaming node publishes and the workbench lists). A simulated site manager then opens, every
``--every-days`` days of the photos, the latest photo of each fixed camera in the workbench
(``nodes.workbench.service.Workbench``, fed those messages) and reviews the readings the page lists (built, not
built, unknown; occluded ones are not listed): for each element that truly shows in the photo (the bench's truth
population: what a person can see) whose reading is wrong or unknown, they press "built" or "not built"
(``Workbench.review_detection``); right readings they leave alone. About one verdict in 20 is itself wrong
(``--misjudge``, seeded): people err too. Each review is the status annotation the workbench publishes; the engine
takes them (``ProgressEngine.add_annotation``, what the streaming node does with the bus's annotations), and the
outputs are scored by ``bench/progress.py``'s ``score`` before and after. Only the scoring and the simulated person
read ``truth/``.

With ``--policies queue:K`` the person instead answers the first K entries of the workbench's review queue
(``Workbench.review_queue``: readings that disagree with the plan, one per element, the farthest off first), each
with "right" or the correction (one in 20 the wrong way).

The reviewed photos' own (photo, element) pairs are then right by construction, so the built F1 rises partly by
definition; the finish dates and the deviation classes at the last photo are the effect to read.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
import time
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import code_version, table, write_section  # noqa: E402
from progress import score, site_photos, truth_population, within  # noqa: E402

from constructaide.bimgeom import glb_to_meshes  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import element_states, load_cameras  # noqa: E402
from nodes.progress import batch  # noqa: E402
from nodes.progress.engine import ProgressEngine  # noqa: E402
from nodes.progress.modelview import LayerRenderer  # noqa: E402
from nodes.workbench.service import Workbench  # noqa: E402
from schemas.messages import Annotation, PhotoEvidence, ProgressUpdate  # noqa: E402


def read_all(inputs: batch.RecordedInputs) -> tuple[ProgressEngine, dict[str, PhotoEvidence]]:
    """:func:`nodes.progress.batch.run_engine`, keeping each photo's PhotoEvidence as it was published."""
    evidence: dict[str, PhotoEvidence] = {}
    return batch.run_engine(inputs, evidence=evidence), evidence


def write_outputs(engine: ProgressEngine, out: Path) -> None:
    """observations.csv / elements.csv / summary.json as ``constructaide progress`` writes them."""
    out.mkdir(parents=True, exist_ok=True)
    batch.write_csv(out / "observations.csv", batch.OBSERVATION_COLUMNS, batch.observation_rows(engine))
    batch.write_csv(out / "elements.csv", batch.ELEMENT_COLUMNS, batch.element_rows(engine))
    times = {r.photo_id: round(r.processing_ms, 1) for r in engine.records.values()}
    summary = {"photos_processed": len(engine.records), "evidence_ms_per_photo": times}
    (out / "summary.json").write_text(json.dumps(summary))


def reviewed_photos(evidence: dict[str, PhotoEvidence], every_days: float, tz: str) -> list[str]:
    """The latest photo of each fixed camera in each window of ``every_days`` local days (counted from the first
    photo's day), in capture order."""
    zone = ZoneInfo(tz)
    days = {pid: dt.datetime.fromtimestamp(e.capture_time_ns / 1e9, zone).date() for pid, e in evidence.items()}
    first = min(days.values())
    latest: dict[tuple[str, int], PhotoEvidence] = {}
    for pid, e in evidence.items():
        if e.camera_id is None:
            continue
        key = (e.camera_id, int((days[pid] - first).days // every_days))
        if key not in latest or e.capture_time_ns > latest[key].capture_time_ns:
            latest[key] = e
    return [e.photo_id for e in sorted(latest.values(), key=lambda e: (e.capture_time_ns, e.photo_id))]


def run(size: str, seed: int, recording: Path, policy: str, misjudge: float) -> dict:
    """One review ``policy``: ``"7"`` (every 7 days the latest photo of each fixed camera) or ``"queue:30"`` (the
    first 30 entries of the workbench's review queue, each answered: confirmed or corrected)."""
    site = ensure_site(size, seed, ROOT / ".cache" / "synth")
    t0 = time.perf_counter()
    inputs = batch.read_inputs(recording)
    assert inputs.model is not None
    engine, evidence = read_all(inputs)
    with tempfile.TemporaryDirectory() as tmp:
        write_outputs(engine, Path(tmp) / "before")
        before = score(site, recording, Path(tmp) / "before")
        # The person at the workbench: the page's messages, their reviews published as annotations.
        published: list[Annotation] = []
        wb = Workbench("bench", publish=lambda _key, msg: published.append(msg))
        wb.apply(inputs.model)
        for p in inputs.photos.values():
            wb.apply(p)
        for e in evidence.values():
            wb.apply(e)
        by_id = site_photos(site)
        cams = load_cameras(site)
        truth_built = element_states(site)["photos"]
        gids = [e.global_id for e in inputs.model.elements]
        meshes = glb_to_meshes(inputs.model.geometry_glb)
        renderer = LayerRenderer()
        renderer.set_model(gids, meshes)
        rng = np.random.default_rng(seed)
        listed = wrong = unknown = misjudged = 0
        if policy.startswith("queue:"):
            # The fused progress the page knows (the streaming node's ProgressUpdates; here the final one).
            elements = tuple(engine.element_progress(g) for g in engine.global_ids)
            wb.apply(ProgressUpdate(site="bench", as_of_ns=engine.as_of_ns, elements=elements, tz=engine.tz))
            items = wb.review_queue(int(policy.split(":")[1]))
            photos = sorted({q["photo_id"] for q in items})
            seen_in: dict[str, set[str]] = {}
            for q in items:
                pid, g, reading = q["photo_id"], q["global_id"], q["reading"]
                rel = by_id[pid]
                if pid not in seen_in:
                    seen_in[pid] = set(truth_population(site, rel, gids, meshes, renderer, cams))
                listed += 1
                if g not in seen_in[pid]:
                    continue  # nothing a person can tell there
                sees = "built" if g in truth_built[rel] else "not_built"
                wrong += sees != reading
                if rng.random() < misjudge:
                    sees, misjudged = ("not_built" if sees == "built" else "built"), misjudged + 1
                verdict = "confirm" if sees == reading else sees
                wb.review_detection(pid, {"global_id": g, "verdict": verdict, "author": "bench"})
            photos_reviewed = len(photos)
        else:
            photos = reviewed_photos(evidence, float(policy), engine.tz)
            photos_reviewed = len(photos)
            for pid in photos:
                rel = by_id[pid]
                visible = set(truth_population(site, rel, gids, meshes, renderer, cams))
                built = set(truth_built[rel])
                for row in wb.progress(pid)["elements"]:
                    reading = row["photo"]["state"]
                    if reading == "occluded":
                        continue  # not listed
                    listed += 1
                    g = row["global_id"]
                    if g not in visible:
                        continue  # nothing a person can tell there
                    sees = "built" if g in built else "not_built"
                    if reading == sees:
                        continue
                    if reading == "unknown":
                        unknown += 1
                    else:
                        wrong += 1
                    if rng.random() < misjudge:
                        sees, misjudged = reading, misjudged + 1  # they look and wrongly agree with the reading
                        continue
                    wb.review_detection(pid, {"global_id": g, "verdict": sees, "author": "bench"})
        wb.close()
        for ann in published:
            engine.add_annotation(ann)
        write_outputs(engine, Path(tmp) / "after")
        after = score(site, recording, Path(tmp) / "after")
    return {
        "site": f"{size} seed {seed}",
        "reviewed_photos": photos_reviewed,
        "listed": listed,
        "wrong": wrong,
        "unknown": unknown,
        "corrections": len(published),
        "misjudged": misjudged,
        "before": before,
        "after": after,
        "secs": time.perf_counter() - t0,
        "recording": recording.name,
    }


def _cells(res: dict) -> list[str]:
    f1 = res["built"]["all"][0][2]
    eo = res["finish"][0]
    d = res["deviation"]
    share = lambda c: d[c][1] / d[c][0] if c in d and d[c][0] else float("nan")  # noqa: E731
    fl = res["flags"]
    return [
        f"{f1:.3f}",
        f"{100 * within(eo):.1f} %",
        f"{100 * share('late'):.0f} / {100 * share('early'):.0f} / {100 * share('on_time'):.0f} %",
        f"{fl['behind'][1]} of {fl['behind'][0]} / {fl['ahead'][1]} of {fl['ahead'][0]}",
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--recording", type=Path, required=True, help="a `constructaide demo` recording of that site")
    ap.add_argument(
        "--policies",
        default="7,1,queue:100",
        help="review policies, a row each: N (every N days the latest photo of each camera), queue:K (the first K "
        "readings of the review queue)",
    )
    ap.add_argument("--misjudge", type=float, default=0.05, help="share of wrong readings the person gets wrong too")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    for policy in args.policies.split(","):
        r = run(args.size, args.seed, args.recording, policy, args.misjudge)
        b, a = _cells(r["before"]), _cells(r["after"])
        rows.append(_row(r, policy, b, a))
    text = table(
        [
            "site",
            "review",
            "photos reviewed",
            "readings listed (built, not built, unknown)",
            "of them wrong / unknown where the person sees the element",
            "reviews pressed",
            "built F1, all photos",
            "finish within ±1 working day",
            "late / early / on time classed right",
            "our behind / ahead flags right",
        ],
        rows,
    )
    print(text)
    if not args.no_write:
        pct = f"{100 * args.misjudge:.0f}"
        body = f"""Recording `{r["recording"]}` of
`constructaide demo --size {args.size} --seed {args.seed} --answer-anchor-requests`, code {code_version()}. The
shipping progress engine reads every photo; then a simulated site manager reviews in the workbench
(`Workbench.review_detection`; a row per policy). "every N days": the latest photo of each fixed camera every N
days; each reading listed (built, not built, unknown) of an element that truly shows there and is wrong or unknown
gets "built" or "not built" ({pct} % of them misjudged: left as read). "first K of the queue": the workbench's
review queue (`Workbench.review_queue`: readings that disagree with the plan, one per element, farthest off
first), each entry whose element truly shows answered: "right" or the correction ({pct} % answered the wrong
way). The engine takes the published status
annotations; scored by `bench/progress.py` before -> after (same definitions; the reviewed (photo, element) pairs
are right by construction after, so built F1 rises partly by definition).

{text}
"""
        write_section(f"progress with a person's review ({r['site']})", body)
    return 0


def _row(r: dict, policy: str, b: list[str], a: list[str]) -> list:
    what = f"first {policy.split(':')[1]} of the queue" if policy.startswith("queue:") else f"every {policy} days"
    return [
        r["site"],
        what,
        r["reviewed_photos"],
        r["listed"],
        f"{r['wrong']} / {r['unknown']}",
        f"{r['corrections']} ({r['misjudged']} misjudged)",
        f"{b[0]} -> {a[0]}",
        f"{b[1]} -> {a[1]}",
        f"{b[2]} -> {a[2]}",
        f"{b[3]} -> {a[3]}",
    ]


if __name__ == "__main__":
    raise SystemExit(main())
