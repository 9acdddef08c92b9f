"""The register node alone as the plain demo feeds it: how many photos it registers, which it asks for, and why.

The shipping register node (``nodes.register.node``) runs in-process on the in-process bus, fed as
``constructaide demo`` feeds it: the site's BIM model (through ``nodes.ingest.revisions.to_bim_model``), the
up-front clicks of the site's ``anchors.json`` (``constructaide.sitedir``), then every photo in capture order;
nobody answers its anchor requests. The node's last Registration per photo is scored against the site's truth
(scoring only): viewing-direction error and the model's reprojection error on pixels showing a BIM element
(% of the width; ``bench/register_stream.score``). A published pose is counted wrong when its view is more than
2 deg off or the model lands more than 0.5 % of the width away. The reasons of the photos left unregistered are
grouped by the first test their message names. Quicker than the whole demo (no occlusion, rendering or recording)
and the same registrations: the register node's inputs are photos, clicks and the BIM only.

Run: ``python bench/register_node.py [--size default] [--seed 0] [--fixed-only] [--set '{"use_bim_depth": false}']``.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import msgspec  # noqa: E402
from _report import code_version, table, write_section  # noqa: E402
from register_stream import score  # noqa: E402

from constructaide import sitedir  # noqa: E402
from constructaide.bim.ifc import load_site_model  # noqa: E402
from constructaide.runtime import start_node  # noqa: E402
from constructaide.runtime.local import LocalBus  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras  # noqa: E402
from nodes.ingest.revisions import to_bim_model  # noqa: E402
from nodes.register.node import SPEC, Config  # noqa: E402
from schemas import keys  # noqa: E402

SITE = "bench"
REASONS = (  # first phrase found in a failure message -> its group
    ("anchor clicks are needed", "no registered photo yet"),
    ("no verified geometry connects", "no verified geometry to the registered photos"),
    ("bumped or view changed", "fixed camera knocked, not re-registered"),
    ("rotation agrees with only", "pose refused: rotation test (repeated texture?)"),
    ("GPS distances", "pose refused: GPS distances"),
    ("explains only", "pose refused: epipolar agreement (repeated texture?)"),
    ("too short a baseline", "relative pose: baseline too short"),
    ("to fix the baseline", "relative pose: no known depth for the baseline"),
    ("disagree (only", "relative pose: baseline lengths disagree"),
    ("matches to triangulated tracks", "too few matches to triangulated tracks"),
)


def reason_group(message: str) -> str:
    """The group of a failed registration's message (the earliest-named test it mentions)."""
    hits = [(message.find(p), g) for p, g in REASONS if p in message]
    return min(hits)[1] if hits else "other"


def run(size: str, seed: int, fixed_only: bool, overrides: dict, cache: Path, verbose: bool = False) -> dict:
    site_dir = ensure_site(size, seed, cache)
    meta = tomllib.loads((site_dir / "site.toml").read_text())
    site_model = load_site_model([site_dir / meta["paths"]["ifc"]], tz=meta["site"]["tz"])
    model = to_bim_model(site_model, SITE, "r1", meta["site"].get("terrain_height_m", 0.0))
    by_rel = sitedir.site_photos(site_dir, SITE)
    anchors = sitedir.anchor_messages(SITE, site_dir, by_rel)
    photos = sorted(by_rel.values(), key=lambda p: (p.capture_time_ns, p.photo_id))
    if fixed_only:
        photos = [p for p in photos if p.camera_id]
        ids = {p.photo_id for p in photos}
        anchors = [a for a in anchors if a.photo_id in ids]
    rel_of = {p.photo_id: rel for rel, p in by_rel.items()}
    cfg = msgspec.convert({"site": SITE, **overrides}, Config)
    t0 = time.perf_counter()
    with LocalBus() as bus, start_node(SPEC, cfg, bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model)
        for a in anchors:
            bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=a.photo_id), a)
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera=p.camera_id), p)
        if not node.wait_idle(7200):
            raise SystemExit("the register node did not settle within 2 h")
        secs = time.perf_counter() - t0
        last = {r.photo_id: r for _k, r in regs.items}
        asked = {m.photo_id for _k, m in needs.items}
    truth = load_cameras(site_dir)
    scores, reasons = [], collections.Counter()
    for p in photos:
        r = last.get(p.photo_id)
        if r is None:
            reasons["no registration published (lost)"] += 1
        elif r.status == "failed":
            reasons[reason_group(r.message)] += 1
            if verbose:
                print(f"unregistered {rel_of[p.photo_id]}: {r.message}", file=sys.stderr)
        else:
            s = score(r, site_dir, rel_of[p.photo_id], truth)
            scores.append((s["reproj_bim_pct_width"], s["angle_deg"], rel_of[p.photo_id], r.method))
    wrong = [s for s in scores if not (s[0] <= 0.5 and s[1] <= 2.0)]
    worst = max(scores, default=(float("nan"), float("nan"), "-", "-"))
    return {
        "set": f"{size} (seed {seed}){', fixed cameras' if fixed_only else ''}",
        "photos": len(photos),
        "anchors": len(anchors),
        "registered": len(scores),
        "asked": len(asked),
        "wrong": wrong,
        "worst": worst,
        "secs": secs,
        "reasons": reasons,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="default")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument("--fixed-only", action="store_true", help="fixed cameras' photos and clicks only")
    ap.add_argument("--set", default="{}", help="register node config overrides (JSON)")
    ap.add_argument("--cache", type=Path, default=ROOT / ".cache" / "synth")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--verbose", action="store_true", help="print each unregistered photo's message")
    args = ap.parse_args(argv)
    overrides = json.loads(args.set)
    results = [run(args.size, s, args.fixed_only, overrides, args.cache, args.verbose) for s in args.seed]
    head = [
        "site",
        "photos",
        "up-front anchors",
        "registered",
        "asked for clicks",
        "published wrong (> 2 deg or > 0.5 % width)",
        "worst model reprojection % width (photo, method)",
        "s",
    ]
    rows = [
        [
            r["set"],
            r["photos"],
            r["anchors"],
            r["registered"],
            r["asked"],
            len(r["wrong"]),
            f"{r['worst'][0]:.2f} ({r['worst'][2]}, {r['worst'][3]})",
            f"{r['secs']:.0f}",
        ]
        for r in results
    ]
    why = [[r["set"], g, n] for r in results for g, n in sorted(r["reasons"].items(), key=lambda kv: -kv[1])]
    text = table(head, rows) + "\n\nPhotos left unregistered, by the first test their message names:\n\n"
    text += table(["site", "reason", "photos"], why)
    wrong = [(r["set"], w[2], w[3], round(w[1], 2), round(w[0], 2)) for r in results for w in r["wrong"]]
    if wrong:
        text += "\n\nPublished wrong (site, photo, method, deg, % width): " + "; ".join(map(str, wrong))
    print(text)
    if not args.no_write:
        cmd = "python bench/register_node.py " + " ".join(argv if argv is not None else sys.argv[1:])
        body = (
            f"Code: {code_version()}. The shipping register node in-process, fed as `constructaide demo` feeds it "
            "(BIM model, the site's anchors.json clicks, every photo in capture order; nobody answers a request"
            + (f"; config overrides {json.dumps(overrides)}" if overrides else "")
            + "). One run (counts, not timings; 's' is informative). Scoring from the site's truth.\n\n"
            + text
        )
        name = f"register node as the plain demo feeds it ({args.size}{', fixed cameras' if args.fixed_only else ''})"
        write_section(name, body, cmd.strip())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
