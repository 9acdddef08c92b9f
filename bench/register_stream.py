"""Streaming registration of fixed-camera frames: fast path (KLT + rotation/zoom LM) vs. the full SIFT path.

Frames: the synthetic site's fixed cameras: accuracy on the small site (960x540, seed 0), timing on the default
site's native 1920x1080 frames (seed 0). A fast-path frame that joins the map as a key frame (every two days per
camera: SIFT, matching, model points) is timed apart from the plain fast-path frames.

Per camera: the first frame is registered from the site's simulated anchor clicks (anchors.json); every later frame
is registered on its own, (a) by a registrar with the fast path (camera id given) and (b) by a registrar forced onto
the full path (camera id withheld: SIFT, matching against registered key images, PnP on BIM-depth points or
homography transfer, local BA). When a frame is refused with an anchor request and anchors.json has clicks for it,
those clicks are supplied, as a user would; otherwise the frame counts as failed.

System inputs: photos, anchors.json, model/building.glb, the IFC schedule (via the ingest loader) and the site's
terrain height. Scoring only reads truth/ (true cameras and depth for checkpoints).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _datasets import load_synth, simulate_synth_clicks  # noqa: E402
from _report import code_version, median, table, write_section  # noqa: E402
from PIL import Image  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.bimgeom import glb_to_meshes  # noqa: E402
from constructaide.schedule4d import standing_elements  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth, load_ids, true_camera  # noqa: E402
from nodes.ingest.photos import exif_focal  # noqa: E402
from nodes.register.bimdepth import MeshDepthLookup  # noqa: E402
from nodes.register.photo import FrameImage, PhotoInput  # noqa: E402
from nodes.register.streaming import StreamConfig, StreamingRegistrar  # noqa: E402


def exif_f(data: bytes) -> float | None:
    """EXIF focal prior in pixels of the stored image, read as the ingest node reads it (system input)."""
    with Image.open(io.BytesIO(data)) as img:
        return exif_focal(img.getexif(), img.width, img.height)[0]


def checkpoints(site: Path, rel: str, intr, T, n: int = 200, seed: int = 0, bim_only: bool = False) -> np.ndarray:
    """Ground-truth 3D points (n, 3) seen in a photo (scoring only: from truth depth); anywhere in the frame, or
    only on pixels that show a BIM element (``bim_only``: what the overlay is drawn on)."""
    depth = load_depth(site, rel)
    rng = np.random.default_rng(seed)
    valid = depth > 0
    if bim_only:
        valid &= load_ids(site, rel) > 0
    ys, xs = np.nonzero(valid)
    pick = rng.choice(len(xs), size=min(n, len(xs)), replace=False)
    px = np.c_[xs[pick], ys[pick]].astype(np.float64)
    z = depth[ys[pick], xs[pick]].astype(np.float64)
    xy = cam.pixels_to_normalized(intr, px)
    return (np.c_[xy, np.ones(len(xy))] * z[:, None]) @ T[:3, :3].T + T[:3, 3]


def score(reg, site: Path, rel: str, cams: dict) -> dict:
    intr_t, T_t = true_camera(site, rel, cams)
    T_e = cam.pose_from_tuple(reg.world_from_camera)
    out = {
        "angle_deg": cam.viewing_angle_deg(T_e, T_t),
        "centre_m": float(np.linalg.norm(T_e[:3, 3] - T_t[:3, 3])),
    }
    for name, bim_only in (("reproj_pct_width", False), ("reproj_bim_pct_width", True)):
        pts = checkpoints(site, rel, intr_t, T_t, bim_only=bim_only)
        p_t, _ = cam.project_points(intr_t, cam.invert_rigid(T_t), pts)
        p_e, _ = cam.project_points(reg.intrinsics, cam.invert_rigid(T_e), pts)
        err = np.linalg.norm(p_t - p_e, axis=1)
        out[name] = float(np.nanmean(err) / intr_t.width_px * 100) if len(err) else float("nan")
    return out


def load_site(size: str = "small"):
    site = ensure_site(size, 0, ROOT / ".cache" / "synth")
    cams = load_cameras(site)
    anchors = {a["image"]: a for a in json.loads((site / "anchors.json").read_text())["anchors"]}
    meta = tomllib.loads((site / "site.toml").read_text())
    from constructaide.bim.ifc import load_site_model

    model = load_site_model([site / meta["paths"]["ifc"]], tz=meta["site"]["tz"])
    meshes = glb_to_meshes((site / meta["paths"]["glb"]).read_bytes())
    ground = meta["site"].get("terrain_height_m", 0.0)
    return site, cams, anchors, model.tasks, meshes, ground


def _published(reg, rec: dict) -> dict:
    """As the register node publishes: the solved registration, then its outline polish when accepted (the record's
    ``reg`` is the last one published, ``solved`` the first, ``polish_ms`` the polish's own time)."""
    solved = rec["reg"]
    rec["solved"] = solved
    t0 = time.perf_counter()
    polished = reg.polish_registration(solved) if solved.status != "failed" else None
    rec["polish_ms"] = (time.perf_counter() - t0) * 1000.0 if solved.status != "failed" else float("nan")
    if polished is not None:
        rec["reg"] = polished
        rec["polished"] = True
    return rec


def run(site, cams, anchors, tasks, meshes, ground, *, fast: bool, cameras: list[str], phones: bool = False):
    """Register every fixed-camera frame (then, optionally, the phone photos); returns per-photo records (each
    registration polished by the model's outline after it, as the node does)."""
    depth = MeshDepthLookup(meshes, elements_at=standing_elements(tasks, meshes.keys()), ground_height_m=ground)
    reg = StreamingRegistrar(StreamConfig(), depth_lookup=depth)
    records = []
    for cam_id in cameras:
        frames = sorted((site / "photos" / cam_id).glob("*.jpg"))
        for i, path in enumerate(frames):
            rel = f"{cam_id}/{path.name}"
            data = path.read_bytes()
            f_px = exif_f(data)
            t_ns = cams[rel]["capture_time_utc_ns"]
            photo = PhotoInput(
                rel, FrameImage(data), camera_id=cam_id if fast else None, capture_time_ns=t_ns, focal_px=f_px
            )
            clicks = anchors.get(rel)
            if i == 0:
                if clicks is None:
                    raise SystemExit(f"no anchor clicks for the first frame {rel}")
                out = reg.register_anchor(photo, *click_arrays(clicks))
                records.append(
                    _published(
                        reg,
                        {
                            "rel": rel,
                            "method": "anchor",
                            "ms": out.registration.processing_ms,
                            "reg": out.registration,
                            "first": True,
                        },
                    )
                )
                continue
            out = reg.register(photo)
            asked = out.needs_anchor is not None
            if asked and clicks is not None:
                photo = PhotoInput(
                    rel,
                    FrameImage(data),
                    camera_id=cam_id if fast else None,
                    capture_time_ns=t_ns,
                    focal_px=f_px,
                )
                out = reg.register_anchor(photo, *click_arrays(clicks))
            r = out.registration
            records.append(
                _published(
                    reg,
                    {
                        "rel": rel,
                        "method": r.method or "failed",
                        "ms": r.processing_ms,
                        "reg": r,
                        "asked_anchor": asked,
                        "message": r.message,
                    },
                )
            )
    if phones:
        synth_cams = {c.name: c for c in load_synth(site)}
        for path in sorted((site / "photos" / "phone").rglob("*.jpg")):
            rel = str(path.relative_to(site / "photos"))
            data = path.read_bytes()
            photo = PhotoInput(
                rel, FrameImage(data), capture_time_ns=cams[rel]["capture_time_utc_ns"], focal_px=exif_f(data)
            )
            clicks = anchors.get(rel)
            if clicks is not None:
                out = reg.register_anchor(photo, *click_arrays(clicks))
                rec = {"rel": rel, "method": "anchor", "ms": 0.0, "reg": out.registration, "phone": True}
                records.append(_published(reg, rec))
                continue
            out = reg.register(photo)
            asked = out.needs_anchor is not None
            method = out.registration.method or "failed"
            if asked:
                # The user answers the request: clicks simulated from truth (bench only, see _datasets).
                px, world = simulate_synth_clicks(site, synth_cams[rel])
                photo = PhotoInput(
                    rel, FrameImage(data), capture_time_ns=cams[rel]["capture_time_utc_ns"], focal_px=exif_f(data)
                )
                out = reg.register_anchor(photo, px, world)
                method = "anchor (simulated clicks)"
            r = out.registration
            rec = {"rel": rel, "method": method, "ms": r.processing_ms, "reg": r, "phone": True, "asked_anchor": asked}
            records.append(_published(reg, rec))
    depth.close()
    return records


def click_arrays(clicks: dict):
    px = np.array([p["pixel"] for p in clicks["points"]], np.float64)
    return px, np.array([p["world"] for p in clicks["points"]], np.float64)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one camera, one timing run")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    code = code_version()  # at the start: the code this run imported
    site, cams, anchors, tasks, meshes, ground = load_site()
    cameras = sorted(p.name for p in (site / "photos").iterdir() if p.is_dir() and p.name.startswith("cam-"))
    if args.quick:
        cameras = cameras[:1]
    runs = 1 if args.quick else 3

    # Accuracy at native resolution.
    acc = {}
    for fast in (True, False):
        recs = run(site, cams, anchors, tasks, meshes, ground, fast=fast, cameras=cameras, phones=fast)
        acc[fast] = [r for r in recs if not r.get("phone")]
        if fast:
            phone_recs = [r for r in recs if r.get("phone")]
    # Timing on native 1920x1080 frames (the default site), several runs of the fast path; the full path once.
    big = load_site("default")
    big_cameras = sorted(p.name for p in (big[0] / "photos").iterdir() if p.is_dir() and p.name.startswith("cam-"))
    if args.quick:
        big_cameras = big_cameras[:1]
    fast_ms, fast_all, fast_share, key_ms, polish_ms = [], [], [], [], []
    for _ in range(runs):
        recs = run(*big, fast=True, cameras=big_cameras)
        fp = [r["ms"] for r in recs if r["method"] == "fastpath" and "key frame" not in r["message"]]
        key_ms += [r["ms"] for r in recs if r["method"].startswith("fastpath") and "key frame" in r["message"]]
        fast_ms.append(median(fp))
        fast_all += fp
        polish_ms += [r["polish_ms"] for r in recs if r["method"] != "failed" and r["polish_ms"] == r["polish_ms"]]
        fast_share.append(len(fp) / max(1, sum(r["method"] != "anchor" for r in recs)))
    recs_full = run(*big, fast=False, cameras=big_cameras)
    full_ms = [r["ms"] for r in recs_full if r["method"] not in ("anchor", "failed")]

    rows = []
    summary = {}
    for fast, recs in acc.items():
        name = "fast path (camera id)" if fast else "full path (no camera id)"
        scored = [(r, score(r["reg"], site, r["rel"], cams)) for r in recs if r["method"] not in ("anchor", "failed")]
        anchors_scored = [score(r["reg"], site, r["rel"], cams) for r in recs if r.get("first")]
        methods: dict[str, int] = {}
        for r in recs:
            if not r.get("first"):
                methods[r["method"]] = methods.get(r["method"], 0) + 1
        asked = sum(bool(r.get("asked_anchor")) for r in recs)
        row = [
            name,
            len(scored),
            sum(r["method"] == "failed" for r in recs),
            asked,
            median([s["angle_deg"] for _, s in scored]),
            median([s["centre_m"] for _, s in scored]),
            median([s["reproj_pct_width"] for _, s in scored]),
            median([s["reproj_bim_pct_width"] for _, s in scored]),
            median([s["reproj_pct_width"] for s in anchors_scored]),
            median([s["reproj_bim_pct_width"] for s in anchors_scored]),
            ", ".join(f"{k} {v}" for k, v in sorted(methods.items())),
        ]
        rows.append(row)
        summary[fast] = row
        for r, s in scored:
            print(
                f"{name:26s} {r['rel']:28s} {r['method']:11s} {r['ms']:7.1f} ms  angle {s['angle_deg']:.3f} deg  "
                f"centre {s['centre_m']:.2f} m  reproj {s['reproj_pct_width']:.2f} % width",
                file=sys.stderr,
            )
    headers = [
        "path",
        "frames registered",
        "failed",
        "anchor requested",
        "median angle err (deg)",
        "median centre err (m)",
        "median reproj (% width)",
        "median reproj on BIM pixels (% width)",
        "anchors' own reproj (% width)",
        "anchors' own reproj on BIM pixels (% width)",
        "methods",
    ]
    acc_table = table(headers, rows)
    phone_rows = []
    for r in phone_recs:
        reg_ = r["reg"]
        if reg_.status == "failed":
            phone_rows.append([r["rel"], "failed", "-", "-", "-", "-", "yes" if r.get("asked_anchor") else "no"])
            continue
        sc = score(reg_, site, r["rel"], cams)
        asked = "yes" if r.get("asked_anchor") else "-"
        phone_rows.append(
            [r["rel"], r["method"], sc["angle_deg"], sc["centre_m"]]
            + [sc["reproj_pct_width"], sc["reproj_bim_pct_width"], asked]
        )
    phone_table = table(
        [
            "phone photo",
            "result",
            "angle err (deg)",
            "centre err (m)",
            "reproj (% width)",
            "reproj on BIM pixels (% width)",
            "anchor requested",
        ],
        phone_rows,
    )
    auto_phone = [r for r in phone_recs if r["reg"].status == "auto" and not r.get("asked_anchor")]
    auto_scores = [score(r["reg"], site, r["rel"], cams) for r in auto_phone]
    phone_summary = table(
        [
            "phone photos",
            "anchors.json clicks",
            "registered without extra anchors",
            "anchor requested",
            "median angle err of those (deg)",
            "worst angle err of those (deg)",
        ],
        [
            [
                len(phone_recs),
                sum(r["method"] == "anchor" for r in phone_recs),
                len(auto_phone),
                sum(bool(r.get("asked_anchor")) for r in phone_recs),
                median([s["angle_deg"] for s in auto_scores]) if auto_scores else "-",
                max(s["angle_deg"] for s in auto_scores) if auto_scores else "-",
            ]
        ],
    )
    print(phone_table)
    print(phone_summary)
    fast_med = median(fast_ms)
    full_med = median(full_ms)
    timing_rows = [
        [
            "fast path (KLT on 0.5x + rotation/zoom LM, 6-DOF if needed)",
            fast_med,
            max(fast_all),
            f"{median(fast_share) * 100:.0f} %",
        ],
        [
            "fast path frame joining the map (+ SIFT, matching, BIM-depth model points, local BA)",
            median(key_ms) if key_ms else float("nan"),
            max(key_ms) if key_ms else float("nan"),
            f"{len(key_ms) // max(runs, 1)} per run",
        ],
        [
            "full path (SIFT + PnP/homography/relative pose + local BA)",
            full_med,
            max(full_ms) if full_ms else float("nan"),
            "-",
        ],
    ]
    timing_rows.append(
        [
            "model outline polish (after the registration is published; its update follows)",
            median(polish_ms) if polish_ms else float("nan"),
            max(polish_ms) if polish_ms else float("nan"),
            "every registered fixed-camera frame",
        ]
    )
    timing_table = table(["1920x1080 frame", "median ms", "max ms", "frames on this path"], timing_rows)
    polish_rows = []
    for fast, recs in acc.items():
        done = [r for r in recs if r["method"] not in ("failed",)]
        before = [score(r["solved"], site, r["rel"], cams)["reproj_bim_pct_width"] for r in done]
        after = [score(r["reg"], site, r["rel"], cams)["reproj_bim_pct_width"] for r in done]
        polish_rows.append(
            [
                "fast path (camera id)" if fast else "full path (no camera id)",
                len(done),
                sum(bool(r.get("polished")) for r in done),
                f"{median(before):.3f} -> {median(after):.3f}",
                f"{max(before):.3f} -> {max(after):.3f}",
            ]
        )
    polish_table = table(
        ["path", "frames (anchors included)", "polished", "median reproj on BIM pixels (% width)", "worst"],
        polish_rows,
    )
    print(polish_table)
    print(acc_table)
    print(timing_table)
    print(f"speed-up full/fast: {full_med / fast_med:.1f}x")
    if not args.no_write:
        n_cam = len(cameras)
        body = f"""Code: {code}; `nodes.register.streaming.StreamingRegistrar` with `StreamConfig()` defaults and
`nodes.register.bimdepth.MeshDepthLookup` (elements standing at the photo's time, the site's terrain height), what
the register node runs for a streamed photo.

Fixed-camera frames of the synthetic site `small` (seed 0; {n_cam} cameras x 6 daily frames, 960x540,
one camera knocked mid-way). First frame per camera registered from the site's simulated anchor clicks; later frames
registered one by one. Scoring against truth/ only (viewing-direction angle, camera-centre distance, mean
reprojection error of 200 true 3D checkpoints per frame in % of the width: anywhere in the frame (ground, context,
building), and only on pixels showing a BIM element, which is where the overlay is drawn).

Accuracy at native 960x540 (the registrations as last published: polished by the model's outline where the polish
was accepted):

{acc_table}

The outline polish (`nodes/register/modelalign.py`, published as an update after the solved registration), solved
-> published:

{polish_table}

Phone photos of the site (registered after the fixed cameras, on the same registrar; anchors.json clicks used
where the site provides them, otherwise the full path):

{phone_table}

{phone_summary}

Timing per native 1920x1080 frame: the fixed cameras of the synthetic `default` site (seed 0; {len(big_cameras)}
cameras x 20 daily frames, first frame anchored from anchors.json); fast path: median over frames, median of
{runs} run(s); full path (camera id withheld): median over frames of one run. Time includes JPEG decoding.

{timing_table}

Speed-up of the fast path over the full path: **{full_med / fast_med:.0f}x** (target: <= 250 ms per frame; the
registration is published at that latency, the outline polish follows as an update).
Every photo carries its EXIF focal as the ingest node reads it (35 mm equivalent, diagonal crop factor); the
anchor solve weighs it against the clicks (maximum a posteriori focal, relative sigma 1.5 %), which holds the
camera distance where nine clicks bunched on a distant, still low building leave focal and distance ambiguous
(before: free focal from the clicks, 2.86 m median centre error and 1.39 % whole-frame reprojection on the fast
path). The fast path's absolute error is the anchor's error carried along (the centre is held at the anchor's
centre; the anchor solve estimates radial k1 when >= 8 spread, non-coplanar clicks constrain it significantly,
and the fast and full paths use the camera's solved k1/k2); tracking adds little (see the tests' relative-rotation
bands).
The knocked camera (cam-east, half-way through the period): with the camera id its first moved frame fails the
fast path and is registered by PnP on the camera's own BIM-depth points, without clicks; without a camera id the
full path matches it against the registered photos; a fixed-camera frame refused with an anchor request gets
clicks only where the site's anchors.json has them (each camera's first frame), otherwise it counts as failed.
Phone photos without clicks in anchors.json are tried on the
full path first; when one is refused with an anchor request it is answered with a careful user's clicks simulated
from truth (visible element corners, 1 px noise; `bench/_datasets.py`), as a person would. "registered without
extra anchors" counts phone photos registered automatically before any request was answered.
"""
        write_section("register-stream", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
