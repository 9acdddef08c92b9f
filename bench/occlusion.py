"""Occlusion masks on the synthetic site: IoU against the true dynamic and static occluder masks.

System inputs only: photos (capture times from EXIF via the ingest code), viewpoint homographies
computed here with SIFT + RANSAC between photos of the same camera folder / among phone photos
(system computation), cameras and sparse points from the register batch pipeline
(``nodes.register.batch.run_batch`` with the site's anchor clicks), the model GLB and the site's
configured ground level (``site.toml``). ``--registration oracle`` replaces registration by the
true cameras and points back-projected from true depth; its rows are labelled as such.

Baselines in the same run: OpenCV MOG2 on the same aligned stacks (dynamic); the paper's plain
static heuristic (flood a superpixel on any occluding point, no ground rule) (static).

    python bench/occlusion.py [--quick] [--size small] [--seed 0] [--registration system|oracle]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import median, table, write_section  # noqa: E402

from constructaide.bimgeom import glb_to_meshes  # noqa: E402
from constructaide.camera import pixels_to_normalized  # noqa: E402
from nodes.occlude.dynamic import DynamicParams, dynamic_mask  # noqa: E402
from nodes.occlude.modeldepth import ModelRenderer  # noqa: E402
from nodes.occlude.stacks import AlignedStack, TimelapseStore, working_size  # noqa: E402
from nodes.register.viewpoints import accept_pair  # noqa: E402
from nodes.occlude.static import (  # noqa: E402
    StaticParams,
    estimate_point_normals,
    static_mask,
)
from schemas.messages import Intrinsics  # noqa: E402


@dataclass
class PhotoRec:
    rel: str  # path relative to photos/
    path: Path
    photo_id: str
    camera_id: str | None
    capture_time_ns: int
    group: str  # camera folder, or "phone"


@dataclass
class Pooled:
    inter: int = 0
    union: int = 0
    ious: list[float] = field(default_factory=list)

    def add(self, mask: np.ndarray, truth: np.ndarray) -> None:
        a, b = mask > 0, truth > 0
        i, u = int(np.count_nonzero(a & b)), int(np.count_nonzero(a | b))
        self.inter += i
        self.union += u
        self.ious.append(1.0 if u == 0 else i / u)

    @property
    def iou(self) -> float:
        return self.inter / self.union if self.union else float("nan")


def load_photos(site: Path) -> list[PhotoRec]:
    from nodes.ingest.photos import photo_from_file

    cfg = tomllib.loads((site / "site.toml").read_text())
    tz = cfg.get("site", {}).get("tz", "UTC")
    out = []
    for p in sorted((site / "photos").rglob("*.jpg")):
        rel = p.relative_to(site / "photos").as_posix()
        group = rel.split("/")[0]
        camera = None if group == "phone" else group
        msg = photo_from_file(p, camera_id=camera, site="bench", tz=tz)
        out.append(PhotoRec(rel, p, msg.photo_id, camera, msg.capture_time_ns, group))
    return out


def sift_homographies(photos: list[PhotoRec], max_width: int = 960) -> dict[tuple[str, str], np.ndarray]:
    """this_from_neighbour (full-res pixels) for accepted pairs within a folder group, both keyed (this, nb)."""
    sift = cv2.SIFT_create(nfeatures=3000)
    feats = {}
    for rec in photos:
        img = cv2.imread(str(rec.path), cv2.IMREAD_GRAYSCALE)
        s = min(1.0, max_width / img.shape[1])
        small = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else img
        kp, desc = sift.detectAndCompute(small, None)
        pts = (np.array([k.pt for k in kp], np.float64) + 0.5) / s - 0.5 if kp else np.zeros((0, 2))
        feats[rec.rel] = (pts, desc)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out: dict[tuple[str, str], np.ndarray] = {}
    groups: dict[str, list[PhotoRec]] = {}
    for rec in photos:
        groups.setdefault(rec.group, []).append(rec)
    for members in groups.values():
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                a, b = members[i], members[j]
                pa, da = feats[a.rel]
                pb, db = feats[b.rel]
                if da is None or db is None or len(pa) < 10 or len(pb) < 10:
                    continue
                knn = matcher.knnMatch(db, da, k=2)
                good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
                if len(good) < 40:
                    continue
                src = pb[[m.queryIdx for m in good]]
                dst = pa[[m.trainIdx for m in good]]
                H, inl = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
                if H is None or inl is None:
                    continue
                # the register node's same-viewpoint rule (paper: one homography explains >= 80 % of matches)
                if accept_pair(H, float(inl.sum()) / len(good), len(good), 0.8, 30):
                    out[(a.photo_id, b.photo_id)] = H
    return out


@dataclass
class Registered:
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    points_m: np.ndarray  # (N, 3) observed in this photo
    pixels_px: np.ndarray  # (N, 2)


def system_registration(site: Path) -> tuple[dict[str, Registered], np.ndarray, dict]:
    """Register with the register batch pipeline. Returns per-rel registrations, the cloud and the report."""
    from nodes.register.batch import run_batch

    with tempfile.TemporaryDirectory() as tmp:
        recon, report = run_batch(site / "photos", site / "anchors.json", Path(tmp), show_progress=False)
    pts, _, obs_p, obs_i, obs_px = recon.sparse_arrays()
    out = {}
    for i, im in enumerate(recon.images):
        if not im.registered:
            continue
        sel = obs_i == i
        out[im.name] = Registered(im.intrinsics, np.asarray(im.world_from_camera), pts[obs_p[sel]], obs_px[sel])
    return out, pts, report


def oracle_registration(site: Path, photos: list[PhotoRec]) -> tuple[dict[str, Registered], np.ndarray, dict]:
    """ORACLE: true cameras, SIFT keypoints back-projected with the true depth (no system registration)."""
    cams = json.loads((site / "truth" / "cameras.json").read_text())
    sift = cv2.SIFT_create(nfeatures=2000)
    out = {}
    allpts = []
    for rec in photos:
        c = cams[rec.rel]
        K = np.asarray(c["K"])
        intr = Intrinsics(
            width_px=c["width"], height_px=c["height"], f_px=K[0, 0], cx_px=K[0, 2], cy_px=K[1, 2], k1=c["k1"], k2=c["k2"]
        )
        wfc = np.asarray(c["world_from_camera"])
        stem = rec.rel[: -len(".jpg")]
        depth = np.load(site / "truth" / "depth" / f"{stem}.npz")
        z = depth[depth.files[0]]
        kp = sift.detect(cv2.imread(str(rec.path), cv2.IMREAD_GRAYSCALE), None)
        px = np.array([k.pt for k in kp], np.float64)
        ui, vi = np.round(px).astype(int).T
        zz = z[vi, ui].astype(np.float64)
        ok = zz > 0
        px, zz = px[ok], zz[ok]
        xy = pixels_to_normalized(intr, px)
        p_cam = np.concatenate([xy * zz[:, None], zz[:, None]], axis=1)
        p_world = p_cam @ wfc[:3, :3].T + wfc[:3, 3]
        out[rec.rel] = Registered(intr, wfc, p_world, px)
        allpts.append(p_world)
    return out, np.concatenate(allpts), {"num_registered": len(out), "num_images": len(photos)}


def mog2_mask(stack: AlignedStack, photo_small: np.ndarray, full_size: tuple[int, int]) -> np.ndarray:
    """OpenCV MOG2 trained on the aligned stack (oldest first), applied to the photo without learning."""
    mog = cv2.createBackgroundSubtractorMOG2(history=max(2, stack.num_views), varThreshold=16, detectShadows=True)
    order = np.argsort(stack.times_ns) if stack.times_ns else np.arange(stack.num_views)
    for i in order:
        mog.apply(stack.images[i], learningRate=-1)
    fg = mog.apply(photo_small, learningRate=0)
    mask = np.where(fg == 255, 255, 0).astype(np.uint8)
    return cv2.resize(mask, full_size, interpolation=cv2.INTER_NEAREST)


def read_truth(site: Path, kind: str, rel: str) -> np.ndarray:
    stem = rel[: -len(".jpg")]
    m = cv2.imread(str(site / "truth" / "masks" / kind / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise FileNotFoundError(f"truth mask {kind}/{stem}.png missing")
    return m


def time_full_hd(
    photos: list[PhotoRec], groups: dict, regs: dict[str, Registered], renderer: ModelRenderer, terrain: float | None,
    cloud_normals: tuple, runs: int,
) -> list[float]:
    """Per-frame wall time (s) of the node's work on frames upscaled to 1920x1080: JPEG decode, stack
    update, aligned stack, dynamic mask + plate, model render, static mask, PNG/JPEG encoding."""
    cam = sorted({p.group for p in photos if p.camera_id is not None})[0]
    frames = [p for p in photos if p.group == cam]
    jpegs = {}
    for p in frames:
        img = cv2.resize(cv2.imread(str(p.path)), (1920, 1080), interpolation=cv2.INTER_CUBIC)
        jpegs[p.photo_id] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    times = []
    for _ in range(runs):
        store = TimelapseStore(working_width_px=480, max_views=6)
        for p in frames:
            t0 = time.perf_counter()
            img = cv2.imdecode(np.frombuffer(jpegs[p.photo_id], np.uint8), cv2.IMREAD_COLOR)
            store.add_photo(p.photo_id, p.camera_id, p.capture_time_ns, img)
            for (a, b), H in groups.items():
                if a == p.photo_id and b in store.frames or b == p.photo_id and a in store.frames:
                    store.set_neighbours(a, {b: H * 1.0})  # homographies are in 960 px; fine for timing
            stack = store.aligned_stack(p.photo_id)
            res = dynamic_mask(img, store.frames[p.photo_id].image_small, stack)
            cv2.imencode(".png", res.mask)
            if res.background is not None:
                cv2.imencode(".jpg", res.background, [cv2.IMWRITE_JPEG_QUALITY, 90])
            reg = regs.get(p.rel)
            if reg is not None:
                w, h, _ = working_size(1920, 1080, 640)
                small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                maps = renderer.render(reg.intrinsics, reg.world_from_camera, w, h)
                n, f = cloud_normals[p.rel]
                st = static_mask(
                    img, small, maps, reg.world_from_camera[:3, 3], reg.points_m, reg.pixels_px * 2.0, n, f, terrain
                )
                cv2.imencode(".png", st.mask)
            if stack.num_views:
                times.append(time.perf_counter() - t0)
    return times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="one timing run instead of three")
    ap.add_argument("--registration", choices=("system", "oracle"), default="system")
    ap.add_argument("--cache", type=Path, default=ROOT / ".cache" / "synth")
    ap.add_argument("--no-write", action="store_true", help="do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)

    from constructaide.synth import ensure_site

    site = ensure_site(args.size, args.seed, args.cache)
    photos = load_photos(site)
    by_rel = {p.rel: p for p in photos}
    t0 = time.perf_counter()
    groups = sift_homographies(photos)
    homography_secs = time.perf_counter() - t0
    print(f"{len(photos)} photos, {len(groups)} accepted same-viewpoint pairs ({homography_secs:.1f} s)", file=sys.stderr)

    t0 = time.perf_counter()
    if args.registration == "system":
        regs, cloud_pts, report = system_registration(site)
        reg_label = "system registration (register batch)"
    else:
        regs, cloud_pts, report = oracle_registration(site, photos)
        reg_label = "ORACLE registration (truth cameras, truth-depth points)"
    reg_secs = time.perf_counter() - t0
    print(f"{reg_label}: {len(regs)}/{len(photos)} registered ({reg_secs:.1f} s)", file=sys.stderr)

    site_cfg = tomllib.loads((site / "site.toml").read_text()).get("site", {})
    terrain = site_cfg.get("terrain_height_m")
    renderer = ModelRenderer(glb_to_meshes((site / "model" / "building.glb").read_bytes()))
    normals_all, flat_all = estimate_point_normals(cloud_pts)
    from scipy.spatial import cKDTree

    tree = cKDTree(cloud_pts) if len(cloud_pts) else None
    cloud_normals = {}
    for rel, reg in regs.items():
        if tree is None or len(reg.points_m) == 0:
            cloud_normals[rel] = (np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
            continue
        _, idx = tree.query(reg.points_m)
        cloud_normals[rel] = (normals_all[idx], flat_all[idx])

    store = TimelapseStore(working_width_px=480, max_views=6)
    images = {}
    for p in photos:
        images[p.rel] = cv2.imread(str(p.path))
        store.add_photo(p.photo_id, p.camera_id, p.capture_time_ns, images[p.rel])
    for (a, b), H in groups.items():
        store.set_neighbours(a, {b: H})

    sys_dyn: dict[str, Pooled] = {}
    base_dyn: dict[str, Pooled] = {}
    sys_st: dict[str, Pooled] = {}
    base_st: dict[str, Pooled] = {}
    n_not_enough = 0
    paper_params = StaticParams(vote_fraction=0.0)
    for p in photos:
        img = images[p.rel]
        H, W = img.shape[:2]
        frame = store.frames[p.photo_id]
        reg = regs.get(p.rel)
        region = None
        maps = None
        if reg is not None:
            w, h, _ = working_size(W, H, 640)
            maps = renderer.render(reg.intrinsics, reg.world_from_camera, w, h)
            dh, dw = frame.image_small.shape[:2]
            region = cv2.resize(maps.has_model.astype(np.uint8), (dw, dh), interpolation=cv2.INTER_NEAREST)
            region = cv2.dilate(region, np.ones((9, 9), np.uint8)) > 0
        stack = store.aligned_stack(p.photo_id)
        res = dynamic_mask(img, frame.image_small, stack, DynamicParams(), region)
        n_not_enough += res.status != "ok"
        truth_d = read_truth(site, "dynamic", p.rel)
        sys_dyn.setdefault(p.group, Pooled()).add(res.mask, truth_d)
        mog = mog2_mask(stack, frame.image_small, (W, H)) if stack.num_views else np.zeros((H, W), np.uint8)
        base_dyn.setdefault(p.group, Pooled()).add(mog, truth_d)

        truth_s = read_truth(site, "static", p.rel)
        if reg is None or maps is None:
            empty = np.zeros((H, W), np.uint8)
            sys_st.setdefault(p.group, Pooled()).add(empty, truth_s)
            base_st.setdefault(p.group, Pooled()).add(empty, truth_s)
            continue
        small = cv2.resize(img, maps.depth_m.shape[::-1], interpolation=cv2.INTER_AREA)
        n, f = cloud_normals[p.rel]
        st = static_mask(img, small, maps, reg.world_from_camera[:3, 3], reg.points_m, reg.pixels_px, n, f, terrain)
        sys_st.setdefault(p.group, Pooled()).add(st.mask, truth_s)
        bs = static_mask(
            img, small, maps, reg.world_from_camera[:3, 3], reg.points_m, reg.pixels_px, n, f, None, paper_params
        )
        base_st.setdefault(p.group, Pooled()).add(bs.mask, truth_s)

    def overall(d: dict[str, Pooled]) -> Pooled:
        o = Pooled()
        for v in d.values():
            o.inter += v.inter
            o.union += v.union
            o.ious += v.ious
        return o

    rows_d = []
    rows_s = []
    for g in sorted(sys_dyn) + ["overall"]:
        sd = overall(sys_dyn) if g == "overall" else sys_dyn[g]
        bd = overall(base_dyn) if g == "overall" else base_dyn[g]
        ss = overall(sys_st) if g == "overall" else sys_st[g]
        bs_ = overall(base_st) if g == "overall" else base_st[g]
        rows_d.append([g, len(sd.ious), round(sd.iou, 3), round(float(np.mean(sd.ious)), 3), round(bd.iou, 3)])
        rows_s.append([g, len(ss.ious), round(ss.iou, 3), round(float(np.mean(ss.ious)), 3), round(bs_.iou, 3)])

    runs = 1 if args.quick else 3
    secs = time_full_hd(photos, groups, regs, renderer, terrain, cloud_normals, runs)
    renderer.close()
    med = median(secs)

    body = [
        f"Site `{args.size}` seed {args.seed}: {len(photos)} photos "
        f"({sum(p.camera_id is not None for p in photos)} fixed-camera, {sum(p.camera_id is None for p in photos)} phone), "
        f"{len(groups)} same-viewpoint pairs from SIFT + RANSAC ({homography_secs:.1f} s). "
        f"Registration: **{reg_label}**, {len(regs)}/{len(photos)} photos registered ({reg_secs:.0f} s). "
        f"Ground level {terrain} m from site.toml. Photos without a stack ({n_not_enough}) or without a registration "
        "count as empty masks. IoU pooled over the photos of a group (sum of intersections / sum of unions); "
        "mean IoU is per photo.",
        "",
        "### dynamic (time-lapse median; baseline OpenCV MOG2 on the same aligned stacks)",
        "",
        table(["group", "photos", "IoU", "mean IoU", "MOG2 IoU"], rows_d),
        "",
        f"### static ({reg_label}; baseline: paper heuristic alone, any-point flood, no ground rule)",
        "",
        table(["group", "photos", "IoU", "mean IoU", "paper-only IoU"], rows_s),
        "",
        f"Runtime per 1920x1080 frame (decode, stack, dynamic + plate, model render, static, encode), "
        f"median of {len(secs)} frames x {runs} run(s): **{med:.3f} s**.",
    ]
    text = "\n".join(body)
    print(text)
    if not args.no_write:
        write_section("occlusion", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
