"""Streaming registration of fixed-camera frames: fast path (KLT + rotation/zoom LM) vs. the full SIFT path.

Frames: the synthetic site's fixed cameras (``constructaide.synth.ensure_site("small", 0, .cache/synth)``, 960x540).
Accuracy is measured at native resolution; timing also on the same frames upscaled 2x to 1920x1080 (bicubic,
JPEG q92) because the `default` site (1920x1080) is not rendered on this machine by the bench.

Per camera: the first frame is registered from the site's simulated anchor clicks (anchors.json); every later frame
is registered on its own, (a) by a registrar with the fast path (camera id given) and (b) by a registrar forced onto
the full path (camera id withheld: SIFT, matching against registered key images, PnP on BIM-depth points or
homography transfer, local BA). When a frame is refused with an anchor request and anchors.json has clicks for it
(the knocked camera), those clicks are supplied, as a user would.

System inputs: photos, anchors.json, model/building.glb, the IFC schedule (via the ingest loader) and the site's
terrain height. Scoring only reads truth/ (true cameras and depth for checkpoints).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tomllib
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _datasets import load_synth, simulate_synth_clicks  # noqa: E402
from _report import median, table, write_section  # noqa: E402
from PIL import Image  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.bimgeom import glb_to_meshes  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth, load_ids, true_camera  # noqa: E402
from nodes.ingest.photos import exif_focal  # noqa: E402
from nodes.register.bimdepth import MeshDepthLookup, standing_elements  # noqa: E402
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


def upscale(data: bytes) -> bytes:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    big = cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_CUBIC)
    return cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()


def load_site():
    site = ensure_site("small", 0, ROOT / ".cache" / "synth")
    cams = load_cameras(site)
    anchors = {a["image"]: a for a in json.loads((site / "anchors.json").read_text())["anchors"]}
    meta = tomllib.loads((site / "site.toml").read_text())
    from nodes.ingest.ifc import load_site_model

    model = load_site_model([site / meta["paths"]["ifc"]], tz=meta["site"]["tz"])
    meshes = glb_to_meshes((site / meta["paths"]["glb"]).read_bytes())
    ground = meta["site"].get("terrain_height_m", 0.0)
    return site, cams, anchors, model.tasks, meshes, ground


def run(
    site, cams, anchors, tasks, meshes, ground, *, fast: bool, scale2: bool, cameras: list[str], phones: bool = False
):
    """Register every fixed-camera frame (then, optionally, the phone photos); returns per-photo records."""
    depth = MeshDepthLookup(meshes, elements_at=standing_elements(tasks, meshes.keys()), ground_height_m=ground)
    reg = StreamingRegistrar(StreamConfig(), depth_lookup=depth)
    records = []
    for cam_id in cameras:
        frames = sorted((site / "photos" / cam_id).glob("*.jpg"))
        for i, path in enumerate(frames):
            rel = f"{cam_id}/{path.name}"
            data = path.read_bytes()
            f_px = exif_f(data)
            if scale2:
                data = upscale(data)
                f_px = None if f_px is None else 2.0 * f_px
            t_ns = cams[rel]["capture_time_utc_ns"]
            photo = PhotoInput(
                rel, FrameImage(data), camera_id=cam_id if fast else None, capture_time_ns=t_ns, focal_px=f_px
            )
            clicks = anchors.get(rel)
            if i == 0:
                if clicks is None:
                    raise SystemExit(f"no anchor clicks for the first frame {rel}")
                out = reg.register_anchor(photo, *click_arrays(clicks, scale2))
                records.append(
                    {
                        "rel": rel,
                        "method": "anchor",
                        "ms": out.registration.processing_ms,
                        "reg": out.registration,
                        "first": True,
                    }
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
                out = reg.register_anchor(photo, *click_arrays(clicks, scale2))
            r = out.registration
            records.append(
                {
                    "rel": rel,
                    "method": r.method or "failed",
                    "ms": r.processing_ms,
                    "reg": r,
                    "asked_anchor": asked,
                    "message": r.message,
                }
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
                out = reg.register_anchor(photo, *click_arrays(clicks, False))
                records.append({"rel": rel, "method": "anchor", "ms": 0.0, "reg": out.registration, "phone": True})
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
            records.append(
                {"rel": rel, "method": method, "ms": r.processing_ms, "reg": r, "phone": True, "asked_anchor": asked}
            )
    depth.close()
    return records


def click_arrays(clicks: dict, scale2: bool):
    px = np.array([p["pixel"] for p in clicks["points"]], np.float64)
    if scale2:
        px = (px + 0.5) * 2 - 0.5
    return px, np.array([p["world"] for p in clicks["points"]], np.float64)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one camera, one timing run")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    site, cams, anchors, tasks, meshes, ground = load_site()
    cameras = sorted(p.name for p in (site / "photos").iterdir() if p.is_dir() and p.name.startswith("cam-"))
    if args.quick:
        cameras = cameras[:1]
    runs = 1 if args.quick else 3

    # Accuracy at native resolution.
    acc = {}
    for fast in (True, False):
        recs = run(site, cams, anchors, tasks, meshes, ground, fast=fast, scale2=False, cameras=cameras, phones=fast)
        acc[fast] = [r for r in recs if not r.get("phone")]
        if fast:
            phone_recs = [r for r in recs if r.get("phone")]
    # Timing at 1920x1080 (upscaled frames), several runs of the fast path; the full path once.
    fast_ms, fast_all, fast_share = [], [], []
    for _ in range(runs):
        recs = run(site, cams, anchors, tasks, meshes, ground, fast=True, scale2=True, cameras=cameras)
        fp = [r["ms"] for r in recs if r["method"] == "fastpath"]
        fast_ms.append(median(fp))
        fast_all += fp
        fast_share.append(len(fp) / max(1, sum(r["method"] != "anchor" for r in recs)))
    recs_full = run(site, cams, anchors, tasks, meshes, ground, fast=False, scale2=True, cameras=cameras)
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
        ["full path (SIFT + PnP/homography + local BA)", full_med, max(full_ms) if full_ms else float("nan"), "-"],
    ]
    timing_table = table(["1920x1080 frame", "median ms", "max ms", "frames on this path"], timing_rows)
    print(acc_table)
    print(timing_table)
    print(f"speed-up full/fast: {full_med / fast_med:.1f}x")
    if not args.no_write:
        n_cam = len(cameras)
        body = f"""Fixed-camera frames of the synthetic site `small` (seed 0; {n_cam} cameras x 6 daily frames, 960x540,
one camera knocked mid-way). First frame per camera registered from the site's simulated anchor clicks; later frames
registered one by one. Scoring against truth/ only (viewing-direction angle, camera-centre distance, mean
reprojection error of 200 true 3D checkpoints per frame in % of the width: anywhere in the frame (ground, context,
building), and only on pixels showing a BIM element, which is where the overlay is drawn).

Accuracy at native 960x540:

{acc_table}

Phone photos of the site (registered after the fixed cameras, on the same registrar; anchors.json clicks used
where the site provides them, otherwise the full path):

{phone_table}

{phone_summary}

Timing per 1920x1080 frame (the same frames upscaled 2x, bicubic, JPEG q92 — the `default` 1920x1080 site is not
rendered by this bench); fast path: median over frames, median of {runs} run(s); full path: median over frames of
one run. Time includes JPEG decoding.

{timing_table}

Speed-up of the fast path over the full path: **{full_med / fast_med:.0f}x** (target: <= 250 ms per frame).
Every photo carries its EXIF focal as the ingest node reads it (35 mm equivalent, diagonal crop factor); the
anchor solve weighs it against the clicks (maximum a posteriori focal, relative sigma 1.5 %), which holds the
camera distance where nine clicks bunched on a distant, still low building leave focal and distance ambiguous
(before: free focal from the clicks, 2.86 m median centre error and 1.39 % whole-frame reprojection on the fast
path). The fast path's absolute error is the anchor's error carried along (the centre is held at the anchor's
centre; the anchor solve estimates radial k1 when >= 8 spread, non-coplanar clicks constrain it significantly,
and the fast and full paths use the camera's solved k1/k2); tracking adds little (see the tests' relative-rotation
bands).
Differences between the two rows come mostly from the knocked camera: without a camera id its first moved frame
finds no confirmed 3D points, so an anchor is requested and supplied (anchors.json), and later frames transfer
from that fresh anchor; with the camera id the moved frame is registered by PnP on the camera's own BIM-depth
points (no user input), carrying that solution's error. Phone photos without clicks in anchors.json are tried on
the full path first; when one is refused with an anchor request (matches dominated by the hoarding's repeated
lettering, BIM-depth points of the anchor not yet confirmed by a second view; before that safeguard they
registered 90-150 degrees off; streaming PnP also refuses poses agreeing with < 70 % of the verified matches'
epipolar geometry, `StreamConfig.min_pose_pair_agreement`) the request is answered with clicks simulated from
truth (12 pixels on BIM elements, true depth back-projected, 1 px noise; `bench/_datasets.py`), as a user would.
"registered without extra anchors" counts phone photos registered automatically before any request was answered.
On this site the phone photos overlap each other and the fixed cameras mostly through the hoarding's repeated
lettering: under the TRUE poses only 4-79 % of the verified phone-to-phone matches and 0-8 % of the
phone-to-fixed-camera matches are epipolar-consistent, and PnP on the anchored phone photo's BIM-depth points
(and on points triangulated from such a pose) finds poses 90-165 degrees off that explain the (wrong) matches
better than the truth does, so no safe automatic registration is available here.
"""
        write_section("register-stream", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
