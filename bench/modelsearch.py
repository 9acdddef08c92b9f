"""Fixed cameras found by the model's outlines alone (nodes/register/modelsearch.py, as the register node calls it),
scored against the synthetic site's truth.

    python bench/modelsearch.py [--sites small:0,small:7,...] [--frames first,middle,last] [--no-write] [--set JSON]

For each site and each fixed camera, the chosen frames (the camera's first, middle and last by capture time) are
searched with :func:`nodes.register.modelsearch.model_anchor` on the site's IFC (the schedule's standing elements at
the frame's date, the terrain plane), the frame's EXIF focal and GPS and the IFC's site reference: what the
register node does before it asks a person for a fixed camera's anchor clicks. Accepted cameras are scored by the
mean reprojection error of the frame's truly visible BIM pixels (% of the width; a camera is right below 0.5 %);
refused ones by where the best hypothesis lay (does the test refuse right cameras?). Only the scoring reads
``truth/``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2  # noqa: E402
import msgspec  # noqa: E402
from _report import code_version, table, write_section  # noqa: E402
from modelalign import bim_error_pct  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.bim.ifc import load_site_model  # noqa: E402
from constructaide.photos import photo_from_file  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth, load_ids, true_camera  # noqa: E402
from nodes.register.bimsite import BimMeshes  # noqa: E402
from nodes.register.modelsearch import SearchParams, model_anchor  # noqa: E402

CACHE = ROOT / ".cache" / "synth"
RIGHT_PCT = 0.5


def frames_of(cams: dict, which: list[str]) -> list[str]:
    """The chosen frames of each fixed camera (relative paths), by capture time."""
    by_cam: dict[str, list[str]] = {}
    for rel, c in cams.items():
        if c.get("camera_id"):
            by_cam.setdefault(c["camera_id"], []).append(rel)
    out = []
    for cid in sorted(by_cam):
        rels = sorted(by_cam[cid], key=lambda r: cams[r]["capture_time_utc_ns"])
        pick = {"first": rels[0], "middle": rels[len(rels) // 2], "last": rels[-1]}
        out += list(dict.fromkeys(pick[w] for w in which))
    return out


def run_site(size: str, seed: int, which: list[str], params: SearchParams) -> list[dict]:
    site = ensure_site(size, seed, CACHE)
    cams = load_cameras(site)
    toml = (site / "site.toml").read_text()
    tz = next((ln.split('"')[1] for ln in toml.splitlines() if ln.startswith("tz")), "UTC")
    terrain = next((float(ln.split("=")[1]) for ln in toml.splitlines() if ln.startswith("terrain_height_m")), 0.0)
    sm = load_site_model([site / "model" / "building.ifc"], tz=tz)
    lookup = BimMeshes.from_site_model(sm, terrain).depth_lookup()  # as the register node builds it
    rows = []
    try:
        for rel in frames_of(cams, which):
            photo = photo_from_file(site / "photos" / rel, cams[rel]["camera_id"], "bench", tz)
            gray = cv2.imread(str(site / "photos" / rel), cv2.IMREAD_GRAYSCALE)
            h, w = gray.shape
            intr = cam.centered_intrinsics(w, h, photo.focal_px or cam.focal_from_fov(w))
            t0 = time.perf_counter()
            details: list = []
            clicks, why = model_anchor(
                lookup, gray, intr, photo.gps, photo.capture_time_ns, params=params, details=details
            )
            secs = time.perf_counter() - t0
            intr_t, wfc_t = true_camera(site, rel, cams)
            depth = load_depth(site, rel) * (load_ids(site, rel) > 0)
            best = details[0] if details else None
            err = bim_error_pct(intr_t, wfc_t, best.intrinsics, best.world_from_camera, depth) if best else float("nan")
            turn = cam.rotation_angle_deg(best.world_from_camera[:3, :3], wfc_t[:3, :3]) if best else float("nan")
            rows.append(
                {
                    "site": f"{size} {seed}",
                    "frame": rel,
                    "accepted": clicks is not None,
                    "err_pct": err,
                    "turn_deg": turn,
                    "support": best.support if best else float("nan"),
                    "chance": best.chance if best else float("nan"),
                    "why": why,
                    "secs": secs,
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    finally:
        lookup.close()
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sites", default="small:0,small:7,small:3,small:5,small:11,small:13,default:0,default:7")
    ap.add_argument("--frames", default="first,middle,last")
    ap.add_argument("--set", default="{}", help="SearchParams overrides (JSON)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--section", default="model search (fixed cameras without clicks)")
    args = ap.parse_args()
    params = msgspec.convert(json.loads(args.set), SearchParams)
    which = args.frames.split(",")
    rows: list[dict] = []
    for spec in args.sites.split(","):
        size, seed = spec.split(":")
        rows += run_site(size, int(seed), which, params)
    summary = []
    for site in dict.fromkeys(r["site"] for r in rows):
        rs = [r for r in rows if r["site"] == site]
        acc = [r for r in rs if r["accepted"]]
        right = [r for r in acc if r["err_pct"] < RIGHT_PCT]
        ref_right = [r for r in rs if not r["accepted"] and r["err_pct"] < RIGHT_PCT]
        summary.append(
            [
                site,
                len(rs),
                len(right),
                len(acc) - len(right),
                f"{len(rs) - len(acc)} ({len(ref_right)})",
                f"{max((r['err_pct'] for r in right), default=float('nan')):.3f}",
                f"{statistics.median(r['secs'] for r in rs):.1f}",
            ]
        )
    t1 = table(
        [
            "site (seed)",
            "frames searched",
            "accepted, right (< 0.5 % width)",
            "accepted, wrong",
            "refused (of them the best hypothesis right)",
            "worst accepted % width",
            "median s per frame",
        ],
        summary,
    )
    t2 = table(
        ["site", "frame", "accepted", "best % width", "best turn deg", "support", "chance", "reason"],
        [
            [
                r["site"],
                r["frame"],
                "yes" if r["accepted"] else "no",
                f"{r['err_pct']:.3f}",
                f"{r['turn_deg']:.2f}",
                f"{r['support']:.3f}",
                f"{r['chance']:.3f}",
                r["why"],
            ]
            for r in rows
        ],
    )
    body = (
        f"Code: {code_version()}. Search parameters: {msgspec.json.encode(params).decode()}.\n\n{t1}\n\n"
        f"Per frame (support and its chance level of the best hypothesis):\n\n{t2}\n"
    )
    print(body)
    if not args.no_write:
        write_section(args.section, body, command="python bench/modelsearch.py " + " ".join(sys.argv[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
