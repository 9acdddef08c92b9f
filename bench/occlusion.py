"""Occlusion masks on synthetic sites: the occlude node's own pipeline scored against the true occluder masks.

Runs ``nodes.occlude.pipeline.OcclusionPipeline`` (the code the occlude node runs, default ``Config`` unless a row
says otherwise) on each site's photos, in capture-time order, one at a time: each photo, then its registration
when it has one, then the idle work (colour-model refreshes) until none is due. Inputs, all from shipping code:
photos through ``constructaide.photos.photo_from_file`` (capture times from EXIF), the model GLB and the site's
ground level (``site.toml``) as the BimModel, cameras and the sparse cloud from the register batch pipeline
(``nodes.register.batch.run_batch``; only points confirmed by guided matching are flagged verified, as the node
publishes them) given before the first photo. No viewpoint groups: the pipeline aligns a fixed camera's frames
itself (what it does for every pair the register node has sent no group for); photos of no fixed camera get no
stack. Registration inputs: ``plain`` (the site's anchors.json only; unregistered photos get no static mask and
count as empty), ``answered`` (every NeedsAnchor request answered with clicks simulated from truth, as a user
would), and, labelled ORACLE (an ablation, never the product's figure), true cameras with truth-depth points.

Rows labelled ablation change one config field; baselines (OpenCV MOG2 on the pipeline's own aligned stacks; the
paper's static heuristic alone on the same inputs) are computed here.

    python bench/occlusion.py [--sizes small default] [--seeds 0 7] [--sites small:0 default:0]
                              [--oracle-sizes small] [--no-write]
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
import msgspec
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import code_version, median, table, write_section  # noqa: E402

from constructaide.camera import pixels_to_normalized, pose_to_tuple, resized_pixels  # noqa: E402
from constructaide.modelview import ModelView  # noqa: E402
from constructaide.photos import photo_from_file  # noqa: E402
from constructaide.sparsecloud import encode_sparse_cloud  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth, load_mask, true_camera  # noqa: E402
from nodes.occlude.pipeline import Config, OcclusionPipeline, decode_sparse  # noqa: E402
from nodes.occlude.stacks import AlignedStack, working_size  # noqa: E402
from nodes.occlude.static import StaticParams, static_mask  # noqa: E402
from schemas.messages import (  # noqa: E402
    SPARSE_POINT_VERIFIED,
    BimModel,
    OcclusionMask,
    Photo,
    Registration,
    SparseCloud,
)

PAPER_STATIC = StaticParams(vote_fraction=0.0, propagation="rounds", propagate_rounds=0)
"""The paper's heuristic alone: any occluding point floods its superpixel; no propagation, no ground rule."""


@dataclass
class PhotoRec:
    rel: str  # path relative to photos/
    photo: Photo
    group: str  # camera folder, or "phone"


@dataclass
class Inputs:
    """What the register node would have published: registrations by photo rel path and the sparse cloud."""

    label: str
    registrations: dict[str, Registration]
    cloud: SparseCloud
    secs: float
    anchors_used: int = 0
    unclickable: int = 0  # photos the simulated user could not click (too little of the model in view)


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


def pooled(groups: dict[str, Pooled], group: str) -> Pooled:
    """The group's figures, or all groups pooled for ``overall``."""
    if group != "overall":
        return groups.get(group, Pooled())
    out = Pooled()
    for p in groups.values():
        out.inter, out.union, out.ious = out.inter + p.inter, out.union + p.union, out.ious + p.ious
    return out


def load_photos(site: Path) -> list[PhotoRec]:
    """The site's photos as the ingest code makes them, in capture-time order."""
    tz = tomllib.loads((site / "site.toml").read_text()).get("site", {}).get("tz", "UTC")
    out = []
    for p in sorted((site / "photos").rglob("*.jpg")):
        rel = p.relative_to(site / "photos").as_posix()
        group = rel.split("/")[0]
        out.append(PhotoRec(rel, photo_from_file(p, None if group == "phone" else group, "bench", tz), group))
    return sorted(out, key=lambda r: (r.photo.capture_time_ns, r.rel))


def _cloud_message(
    photo_ids: list[str], points: np.ndarray, verified: np.ndarray, obs_p: np.ndarray, obs_i: np.ndarray, px: np.ndarray
) -> SparseCloud:
    arrays = {
        "photo_ids": photo_ids,
        "points_xyz": points,
        "colors_rgb": np.zeros((len(points), 3), np.uint8),
        "obs_point": obs_p,
        "obs_photo": obs_i,
        "obs_pixel": px,
        "point_flags": np.where(verified, SPARSE_POINT_VERIFIED, 0),
    }
    return encode_sparse_cloud("bench", 1, arrays)


def write_answered_anchor_file(site: Path, photos: list[PhotoRec], path: Path) -> int:
    """The site's anchors.json clicks, then, flagged ``on_request`` (used only for photos the batch asks an anchor
    for), the simulated user's clicks (``constructaide.synth.clicker.simulated_clicks``: 12 model pixels, 1 px
    noise, as the demo answers NeedsAnchor requests) on every other photo that shows enough of the model to click.
    Returns how many photos nobody could click."""
    from constructaide.synth.clicker import simulated_clicks

    doc = json.loads((site / "anchors.json").read_text())
    have = {a["image"] for a in doc["anchors"]}
    cams = load_cameras(site)
    unclickable = 0
    for rec in photos:
        if rec.rel in have:
            continue
        try:
            px, world = simulated_clicks(site, rec.rel, cameras=cams)
        except ValueError:  # too little of the model in view
            unclickable += 1
            continue
        points = [{"pixel": list(map(float, p)), "world": list(map(float, w))} for p, w in zip(px, world, strict=True)]
        doc["anchors"].append({"image": rec.rel, "points": points, "on_request": True})
    path.write_text(json.dumps(doc))
    return unclickable


def batch_inputs(site: Path, photos: list[PhotoRec], answer_anchor_requests: bool) -> Inputs:
    """Registrations and the sparse cloud of the register batch pipeline (``constructaide register``), with the
    site's anchor file, or with ``answer_anchor_requests`` :func:`write_answered_anchor_file`'s."""
    from nodes.register.batch import run_batch

    by_rel = {r.rel: r for r in photos}
    t0 = time.perf_counter()
    unclickable = 0
    with tempfile.TemporaryDirectory() as tmp:
        anchors = site / "anchors.json"
        if answer_anchor_requests:
            anchors = Path(tmp) / "anchors-answered.json"
            unclickable = write_answered_anchor_file(site, photos, anchors)
        recon, report = run_batch(site / "photos", anchors, Path(tmp) / "out", show_progress=False)
    secs = time.perf_counter() - t0
    pts, _, obs_p, obs_i, obs_px = recon.sparse_arrays()
    finite = np.all(np.isfinite(recon.points), axis=1)
    verified = (
        recon.point_verified[finite] if recon.densified else np.ones(len(pts), bool)
    )  # only points confirmed by guided matching judge the model (the node's flags)
    regs = {}
    for im in recon.images:
        if im.registered:
            regs[im.name] = Registration(
                site="bench",
                photo_id=by_rel[im.name].photo.photo_id,
                camera_id=by_rel[im.name].photo.camera_id,
                intrinsics=im.intrinsics,
                world_from_camera=pose_to_tuple(np.asarray(im.world_from_camera)),
                status="auto",
                method="batch",
            )
    ids = [by_rel[im.name].photo.photo_id for im in recon.images]
    cloud = _cloud_message(ids, pts, verified, obs_p, obs_i, obs_px)
    n_anchors = sum(im.get("status") == "anchor" for im in report.get("images", []))
    label = "answered" if answer_anchor_requests else "plain"
    return Inputs(label, regs, cloud, secs, n_anchors, unclickable)


def oracle_inputs(site: Path, photos: list[PhotoRec]) -> Inputs:
    """ORACLE: true cameras, SIFT keypoints back-projected with the true depth (no system registration)."""
    t0 = time.perf_counter()
    cams = load_cameras(site)
    sift = cv2.SIFT.create(nfeatures=2000)
    regs, pts_all, obs_i, obs_px = {}, [], [], []
    for i, rec in enumerate(photos):
        intr, wfc = true_camera(site, rec.rel, cams)
        z = load_depth(site, rec.rel)
        grey = cv2.imdecode(np.frombuffer(rec.photo.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        px = np.array([k.pt for k in sift.detect(grey, None)], np.float64).reshape(-1, 2)
        zz = z[np.round(px[:, 1]).astype(int), np.round(px[:, 0]).astype(int)].astype(np.float64)
        px, zz = px[zz > 0], zz[zz > 0]
        xy = pixels_to_normalized(intr, px)
        pts = np.c_[xy * zz[:, None], zz] @ wfc[:3, :3].T + wfc[:3, 3]
        regs[rec.rel] = Registration(
            site="bench",
            photo_id=rec.photo.photo_id,
            camera_id=rec.photo.camera_id,
            intrinsics=intr,
            world_from_camera=pose_to_tuple(wfc),
            status="auto",
            method="oracle",
        )
        pts_all.append(pts)
        obs_i.append(np.full(len(pts), i))
        obs_px.append(px)
    pts = np.concatenate(pts_all)
    cloud = _cloud_message(
        [r.photo.photo_id for r in photos],
        pts,
        np.ones(len(pts), bool),
        np.arange(len(pts)),
        np.concatenate(obs_i),
        np.concatenate(obs_px),
    )
    return Inputs("ORACLE", regs, cloud, time.perf_counter() - t0)


@dataclass
class Run:
    """The last mask of each kind per photo rel, and the pipeline (its stores) after the run."""

    config: Config
    masks: dict[tuple[str, str], np.ndarray]
    status: dict[tuple[str, str], OcclusionMask]
    pipeline: OcclusionPipeline
    frame_secs: list[float]  # per fixed-camera frame after its camera's first: photo + registration handling
    idle_secs: list[float]  # per photo: the idle work drained after it


def run_pipeline(site: Path, photos: list[PhotoRec], inputs: Inputs, config: Config) -> Run:
    """Feed the site through an OcclusionPipeline as the node receives it (see the module docstring)."""
    rel_of = {r.photo.photo_id: r.rel for r in photos}
    masks: dict[tuple[str, str], np.ndarray] = {}
    status: dict[tuple[str, str], OcclusionMask] = {}

    def emit(msg: OcclusionMask, mask: np.ndarray | None) -> None:
        key = (rel_of[msg.photo_id], msg.kind)
        status[key] = msg
        if mask is None:
            masks.pop(key, None)
        else:
            masks[key] = mask

    terrain = tomllib.loads((site / "site.toml").read_text()).get("site", {}).get("terrain_height_m")
    model = BimModel(
        site="bench",
        revision="r1",
        geometry_glb=(site / "model" / "building.glb").read_bytes(),
        terrain_height_m=terrain,
    )
    pipe = OcclusionPipeline(config, emit, site="bench")
    pipe.set_model(model)
    pipe.set_sparse(inputs.cloud)
    frame_secs, idle_secs, seen_camera = [], [], set()
    for rec in photos:
        t0 = time.perf_counter()
        pipe.add_photo(rec.photo)
        reg = inputs.registrations.get(rec.rel)
        if reg is not None:
            pipe.add_registration(reg)
        t1 = time.perf_counter()
        while pipe.idle():
            pass
        idle_secs.append(time.perf_counter() - t1)
        if rec.photo.camera_id is not None:
            if rec.photo.camera_id in seen_camera:
                frame_secs.append(t1 - t0)
            seen_camera.add(rec.photo.camera_id)
    return Run(config, masks, status, pipe, frame_secs, idle_secs)


def mog2_mask(stack: AlignedStack, photo_small: np.ndarray, full_size: tuple[int, int]) -> np.ndarray:
    """Baseline: OpenCV MOG2 trained on the aligned stack (oldest first), applied to the photo without learning."""
    mog = cv2.createBackgroundSubtractorMOG2(history=max(2, stack.num_views), varThreshold=16, detectShadows=True)
    order = np.argsort(stack.times_ns) if stack.times_ns else np.arange(stack.num_views)
    for i in order:
        mog.apply(stack.images[i], learningRate=-1)
    fg = mog.apply(photo_small, learningRate=0)
    return cv2.resize(np.where(fg == 255, 255, 0).astype(np.uint8), full_size, interpolation=cv2.INTER_NEAREST)


@dataclass
class DynamicScore:
    node: dict[str, Pooled]
    mog2: dict[str, Pooled]
    node_transient: dict[str, Pooled]
    mog2_transient: dict[str, Pooled]
    persistent_frac: float
    no_stack: int


def score_dynamic(site: Path, photos: list[PhotoRec], run: Run) -> DynamicScore:
    """Dynamic IoU per group of the run's last masks; MOG2 on the same stacks; scores outside persistent truth."""
    store = run.pipeline.store
    by_id = {r.photo.photo_id: r for r in photos}
    truth = {r.rel: load_mask(site, r.rel, "dynamic") for r in photos}
    s = DynamicScore({}, {}, {}, {}, 0.0, 0)
    persistent_px = truth_px = 0
    for rec in photos:
        t = truth[rec.rel]
        H, W = t.shape
        frame = store.frames[rec.photo.photo_id]
        stack = store.aligned_stack(rec.photo.photo_id)
        mask = run.masks.get((rec.rel, "dynamic"), np.zeros((H, W), np.uint8))
        mog = mog2_mask(stack, frame.image_small, (W, H)) if stack.num_views else np.zeros((H, W), np.uint8)
        s.no_stack += stack.num_views == 0
        s.node.setdefault(rec.group, Pooled()).add(mask, t)
        s.mog2.setdefault(rec.group, Pooled()).add(mog, t)
        # analysis only: true occluder pixels at the same place in at least half of the aligned neighbours cannot be
        # told from background by any time-lapse method; score without them too
        ignore = np.zeros((H, W), bool)
        if stack.num_views:
            votes = sum(
                (store.warp_full_image(rec.photo.photo_id, nid, truth[by_id[nid].rel].astype(np.uint8)) > 0).astype(
                    np.int32
                )
                for nid in stack.photo_ids
            )
            dh, dw = frame.image_small.shape[:2]
            small_truth = cv2.resize(t.astype(np.uint8), (dw, dh), interpolation=cv2.INTER_NEAREST) > 0
            persistent = (small_truth & (votes * 2 >= stack.num_views)).astype(np.uint8)
            ignore = cv2.resize(persistent, (W, H), interpolation=cv2.INTER_NEAREST) > 0
        persistent_px += int(np.count_nonzero(ignore & t))
        truth_px += int(np.count_nonzero(t))
        keep = ~ignore
        s.node_transient.setdefault(rec.group, Pooled()).add((mask > 0) & keep, t & keep)
        s.mog2_transient.setdefault(rec.group, Pooled()).add((mog > 0) & keep, t & keep)
    s.persistent_frac = persistent_px / max(truth_px, 1)
    return s


def score_static(site: Path, photos: list[PhotoRec], run: Run) -> dict[str, Pooled]:
    """Static IoU per group of the run's last static masks (a photo without one counts as empty)."""
    out: dict[str, Pooled] = {}
    for rec in photos:
        t = load_mask(site, rec.rel, "static")
        out.setdefault(rec.group, Pooled()).add(run.masks.get((rec.rel, "static"), np.zeros(t.shape, np.uint8)), t)
    return out


def paper_static(site: Path, photos: list[PhotoRec], inputs: Inputs, view: ModelView) -> dict[str, Pooled]:
    """Baseline: the paper's static heuristic alone (``PAPER_STATIC``) on the same registrations and cloud."""
    cloud = decode_sparse(inputs.cloud)
    out: dict[str, Pooled] = {}
    for rec in photos:
        t = load_mask(site, rec.rel, "static")
        reg = inputs.registrations.get(rec.rel)
        if reg is None or reg.intrinsics is None:
            out.setdefault(rec.group, Pooled()).add(np.zeros(t.shape, np.uint8), t)
            continue
        img = cv2.imdecode(np.frombuffer(rec.photo.data, np.uint8), cv2.IMREAD_COLOR)
        H, W = img.shape[:2]
        w, h, _ = working_size(W, H, Config().static_working_width_px)
        wfc = np.asarray(reg.world_from_camera).reshape(4, 4)
        maps = view.maps(reg.intrinsics, wfc, w, h)
        sel = cloud.obs_photo == cloud.photo_index.get(rec.photo.photo_id, -1)
        idx = cloud.obs_point[sel]
        px = resized_pixels(cloud.obs_pixel[sel], (reg.intrinsics.width_px, reg.intrinsics.height_px), (W, H))
        small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        res = static_mask(
            img,
            small,
            maps,
            wfc[:3, 3],
            cloud.points_m[idx],
            px,
            cloud.normals[idx],
            cloud.flatness[idx],
            None,
            PAPER_STATIC,
        )
        out.setdefault(rec.group, Pooled()).add(res.mask, t)
    return out


def _r(x: float) -> float:
    return round(x, 3)


@dataclass
class SiteResult:
    name: str
    size: str
    seed: int
    photos: int
    lines: list[str]
    summary: list[object]


def bench_site(site: Path, size: str, seed: int, oracle: bool) -> SiteResult:
    photos = load_photos(site)
    groups = sorted({r.group for r in photos}) + ["overall"]
    n_fixed = sum(r.photo.camera_id is not None for r in photos)
    print(f"{site.name}: {len(photos)} photos", file=sys.stderr)
    inputs = [batch_inputs(site, photos, False), batch_inputs(site, photos, True)]
    if oracle:
        inputs.append(oracle_inputs(site, photos))
    for inp in inputs:
        print(f"  {inp.label}: {len(inp.registrations)}/{len(photos)} registered ({inp.secs:.0f} s)", file=sys.stderr)
    product = Config(site="bench")
    off = msgspec.structs.replace(product, dynamic_appearance="off")
    runs: dict[str, Run] = {}
    for inp in inputs:
        t0 = time.perf_counter()
        runs[inp.label] = run_pipeline(site, photos, inp, product)
        print(f"  pipeline on {inp.label}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    runs["plain, colour model off"] = run_pipeline(site, photos, inputs[0], off)
    unbounded = msgspec.structs.replace(product, dynamic_max_grow_px=None)
    runs["plain, growth unbounded"] = run_pipeline(site, photos, inputs[0], unbounded)
    dyn = score_dynamic(site, photos, runs["plain"])
    dyn_off = score_dynamic(site, photos, runs["plain, colour model off"])
    dyn_unb = score_dynamic(site, photos, runs["plain, growth unbounded"])
    view = ModelView(runs["plain"].pipeline.meshes)
    statics = {
        inp.label: (score_static(site, photos, runs[inp.label]), paper_static(site, photos, inp, view))
        for inp in inputs
    }
    view.close()
    for r in runs.values():
        r.pipeline.close()

    rows_d = [
        [
            g,
            len(pooled(dyn.node, g).ious),
            _r(pooled(dyn.node, g).iou),
            _r(float(np.mean(pooled(dyn.node, g).ious))),
            _r(pooled(dyn_off.node, g).iou),
            _r(pooled(dyn_unb.node, g).iou),
            _r(pooled(dyn.mog2, g).iou),
            _r(pooled(dyn.node_transient, g).iou),
            _r(pooled(dyn.mog2_transient, g).iou),
        ]
        for g in groups
    ]
    fixed_res = next((f"{r.photo.width_px}x{r.photo.height_px}" for r in photos if r.photo.camera_id), "-")
    plain = runs["plain"]
    lines = [
        f"### `{site.name}` (size {size}, seed {seed}): {len(photos)} photos ({n_fixed} fixed-camera, "
        f"{len(photos) - n_fixed} phone), fixed frames {fixed_res}",
        "",
        f"Dynamic: model region from the `plain` registration ({len(inputs[0].registrations)}/{len(photos)} "
        f"registered); {dyn.no_stack} photos without a stack (colour model alone). Colour model off: the ablation "
        f'`dynamic_appearance="off"` (time-lapse masks alone); growth unbounded: `dynamic_max_grow_px=None` (the '
        "hysteresis floods the whole weak component, as before 2026-12-06). Transient truth (analysis only): "
        f"{dyn.persistent_frac:.0%} of the true dynamic-occluder pixels stand at the same place in at least half "
        "of the photo's aligned neighbours (cabins, the crane mast); the transient columns score outside them.",
        "",
        table(
            [
                "group",
                "photos",
                "dynamic IoU (node)",
                "mean IoU",
                "ablation: colour model off",
                "ablation: growth unbounded",
                "MOG2 (baseline)",
                "node, transient truth",
                "MOG2, transient truth",
            ],
            rows_d,
        ),
        "",
    ]
    for inp in inputs:
        st, paper = statics[inp.label]
        what = {
            "plain": "registration from the site's anchors.json only",
            "answered": f"every anchor request answered ({inp.anchors_used} anchors used; "
            f"{inp.unclickable} photos show too little of the model to click)",
            "ORACLE": "ORACLE ablation: true cameras and truth-depth points, not a system figure",
        }[inp.label]
        lines += [
            f"Static, `{inp.label}` ({what}): {len(inp.registrations)}/{len(photos)} registered, "
            f"{len(inp.cloud.points_xyz_f32) // 12} sparse points ({inp.secs:.0f} s).",
            "",
            table(
                ["group", "photos", "static IoU (node)", "mean IoU", "paper heuristic alone (baseline)"],
                [
                    [
                        g,
                        len(pooled(st, g).ious),
                        _r(pooled(st, g).iou),
                        _r(float(np.mean(pooled(st, g).ious))),
                        _r(pooled(paper, g).iou),
                    ]
                    for g in groups
                ],
            ),
            "",
        ]
    lines += [
        f"Node work per fixed-camera frame ({fixed_res}, `plain` run, every frame after its camera's first): photo "
        f"and registration handled, recomputes included, median **{median(plain.frame_secs):.2f} s** over "
        f"{len(plain.frame_secs)} frames; idle work (colour-model refreshes) after each photo, median "
        f"{median(plain.idle_secs):.2f} s (JPEG decode and PNG/JPEG encoding included; machine shared).",
        "",
    ]
    summary = [
        f"{size} (seed {seed})",
        len(photos),
        _r(pooled(dyn.node, "overall").iou),
        _r(pooled(dyn_off.node, "overall").iou),
        _r(pooled(dyn.mog2, "overall").iou),
        f"{_r(pooled(statics['plain'][0], 'overall').iou)} ({len(inputs[0].registrations)}/{len(photos)})",
        f"{_r(pooled(statics['answered'][0], 'overall').iou)} ({inputs[1].anchors_used} anchors)",
        _r(pooled(statics["answered"][1], "overall").iou),
        _r(pooled(statics["ORACLE"][0], "overall").iou) if oracle else "-",
        f"{median(plain.frame_secs):.2f} ({fixed_res})",
    ]
    return SiteResult(site.name, size, seed, len(photos), lines, summary)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["small"], help="synthetic site sizes (ensure_site)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 7], help="synthetic site seeds (0: tuned on; 7: not)")
    ap.add_argument(
        "--sites", nargs="+", default=None, metavar="SIZE:SEED", help="size:seed pairs instead of --sizes x --seeds"
    )
    ap.add_argument("--site-dir", type=Path, default=None, help="an existing site folder instead (size/seed unknown)")
    ap.add_argument(
        "--oracle-sizes", nargs="*", default=["small"], help="sizes that also get the ORACLE ablation (true cameras)"
    )
    ap.add_argument("--cache", type=Path, default=ROOT / ".cache" / "synth")
    ap.add_argument("--section", default="occlusion", help="BENCHMARKS.md section to write (default: occlusion)")
    ap.add_argument("--no-write", action="store_true", help="do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)
    code = code_version()  # at the start: the code this run imported

    from constructaide.synth import ensure_site

    if args.sites:
        pairs = [(s.split(":")[0], int(s.split(":")[1])) for s in args.sites]
    else:
        pairs = [(size, seed) for size in args.sizes for seed in args.seeds]
    results = []
    for size, seed in [("?", -1)] if args.site_dir is not None else pairs:
        site = args.site_dir if args.site_dir is not None else ensure_site(size, seed, args.cache)  # one at a time
        results.append(bench_site(site, size, seed, oracle=size in args.oracle_sizes))
        print("\n".join(results[-1].lines), flush=True)  # progress: a site's figures as soon as they are in
    body = [
        f"Code: {code}; `nodes.occlude.pipeline.OcclusionPipeline` with `Config()` defaults "
        f"(`{msgspec.json.encode(Config(site='bench')).decode()}`) unless a column names an ablation. "
        "Inputs and protocol: `bench/occlusion.py` docstring (photos one at a time in capture order, cameras and "
        "sparse cloud from the register batch pipeline, no viewpoint groups). IoU pooled over a group's photos "
        "(sum of intersections / sum of unions); a photo without a mask counts as empty. Seed 0 is the seed the "
        "thresholds were tuned on; seed 7 was never used for tuning.",
        "",
        table(
            [
                "site",
                "photos",
                "dynamic IoU (node)",
                "ablation: colour model off",
                "MOG2 (baseline)",
                "static IoU, plain (registered)",
                "static IoU, anchor requests answered",
                "paper static heuristic (baseline, answered)",
                "ORACLE static (true cameras)",
                "s per fixed frame",
            ],
            [r.summary for r in results],
        ),
        "",
    ]
    for r in results:
        body += r.lines
    text = "\n".join(body)
    print(text)
    if not args.no_write:
        write_section(args.section, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
