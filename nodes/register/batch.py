"""``constructaide register``: model-assisted SfM over a folder of photos (batch mode).

Writes a COLMAP text model (cameras.txt, images.txt, points3D.txt) in the model frame and ``report.json``
(registered / unregistered images with reasons, per-image RMS, timings). Anchor file format::

    {"anchors": [{"image": "IMG_0001.jpg", "points": [{"pixel": [u, v], "world": [x, y, z]}, ...]}],
     "focal_px": 1520.0}

``image`` is the posix path relative to ``--images``; ``pixel`` is OpenCV convention; ``world`` in model units.
An anchor may carry ``"on_request": true``: its clicks are held back until the algorithm asks for that image's
anchor (a scripted user answering requests, as the benchmarks simulate); the others count as given up front (an
automatic registration of such an image is checked against them, ``MapperConfig.check_auto_with_clicks``).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import cv2
import msgspec
import numpy as np
from tqdm import tqdm

from constructaide import camera as cam
from constructaide.anchorsolve import DegenerateAnchors
from constructaide.bim.ifc import load_site_model
from constructaide.errors import UserError
from constructaide.geo import exif_gps
from constructaide.sitedir import camera_of
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.bimsite import BimMeshes
from nodes.register.colmap_io import ColmapImage, ColmapModel, write_text_model
from nodes.register.config import MapperConfig
from nodes.register.densify import DensifyParams, densify_reconstruction
from nodes.register.features import Features, extract_features
from nodes.register.mapper import register_anchor
from nodes.register.modelalign import AlignParams, Polished, PolishPolicy, ViewPolish, polish_registration
from nodes.register.modelsearch import OutlineCheck, model_anchor
from nodes.register.phonesearch import TextureFrame, nearest_fixed_frames, phone_anchor_in, retexture
from nodes.register.pose import epipolar_agreement
from nodes.register.recon import Clicks, Reconstruction, add_image, focal_prior
from nodes.register.sfm import reconstruct
from schemas.messages import GeoPoint, Intrinsics

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"}
DEFAULT_DENSIFY = DensifyParams()
DEFAULT_POLISH = AlignParams()
# Longest image side (px) features are detected at, as COLMAP's default max_image_size: a 6 Mpx photo keeps its
# full resolution.
DEFAULT_MAX_SIDE_PX = 3200


def looks_like_site_layout(images_dir: Path) -> bool:
    """Whether ``images_dir`` is laid out as a site's photos folder (a ``phone/`` sub-folder, or a ``site.toml``
    beside it): then its first-level folders are most likely fixed cameras (``--camera-folders``)."""
    root = Path(images_dir)
    return (root / "phone").is_dir() or (root.parent / "site.toml").is_file()


def find_images(images_dir: Path) -> list[tuple[str, Path]]:
    """Images under ``images_dir`` (recursive), sorted, as (posix name relative to the folder, path)."""
    root = Path(images_dir)
    if not root.is_dir():
        raise UserError(f"--images {root} is not a folder")
    found = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    return [(p.relative_to(root).as_posix(), p) for p in found]


class AnchorFile(NamedTuple):
    """Clicks by image name (file order), the optional focal prior (px) and the images whose clicks are held back
    until asked for (``"on_request": true``)."""

    clicks: dict[str, Clicks]
    focal_px: float | None
    on_request: frozenset[str] = frozenset()


def load_anchor_file(path: Path) -> AnchorFile:
    """Parse the anchor file: clicks by image name (in file order), the optional focal prior (px) and the images
    flagged ``on_request``."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"anchor file {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"anchor file {path} is not valid JSON: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("anchors"), list) or not doc["anchors"]:
        raise UserError(f"anchor file {path} needs a non-empty list 'anchors'")
    focal = doc.get("focal_px")
    if focal is not None and (not isinstance(focal, int | float) or not math.isfinite(focal) or focal <= 0):
        raise UserError(f"anchor file {path}: focal_px must be a positive number, got {focal!r}")
    out: dict[str, Clicks] = {}
    held: set[str] = set()
    for k, a in enumerate(doc["anchors"]):
        if not isinstance(a, dict) or not isinstance(a.get("image"), str) or not isinstance(a.get("points"), list):
            raise UserError(f"anchor file {path}: anchors[{k}] needs 'image' (string) and 'points' (list)")
        px, world = [], []
        for j, p in enumerate(a["points"]):
            try:
                u, v = (float(x) for x in p["pixel"])
                x, y, z = (float(c) for c in p["world"])
            except (KeyError, TypeError, ValueError):
                raise UserError(
                    f"anchor file {path}: anchors[{k}].points[{j}] needs 'pixel' [u, v] and 'world' [x, y, z]"
                ) from None
            px.append((u, v))
            world.append((x, y, z))
        if len(px) < 4:
            raise UserError(f"anchor file {path}: image {a['image']} has {len(px)} clicks, at least 4 are needed")
        if a["image"] in out:
            raise UserError(f"anchor file {path}: image {a['image']} is listed twice")
        out[a["image"]] = (np.array(px, float), np.array(world, float))
        flag = a.get("on_request", False)
        if not isinstance(flag, bool):
            raise UserError(f"anchor file {path}: anchors[{k}].on_request must be true or false, got {flag!r}")
        if flag:
            held.add(a["image"])
    if len(held) == len(out):
        raise UserError(f"anchor file {path}: every anchor is 'on_request'; at least one must be given up front")
    return AnchorFile(out, (float(focal) if focal is not None else None), frozenset(held))


def _png_exif_chunk(path: Path) -> bytes | None:
    """Payload of a PNG's eXIf chunk, found by walking chunk headers (no decoding), or None."""
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return None
            length, kind = int.from_bytes(head[:4], "big"), head[4:]
            if kind == b"eXIf":
                return fh.read(length)
            if kind == b"IEND":
                return None
            fh.seek(length + 4, 1)


def _read_exif(path: Path):
    """The image's EXIF (a PIL ``Image.Exif``) and stored size (w, h), read without decoding the pixels (Pillow's
    PNG getexif() decodes the whole image to reach an eXIf chunk after the pixels; the chunk headers are walked
    instead)."""
    from PIL import Image

    with Image.open(path) as img:
        size = img.size
        raw = img.info.get("exif") or (_png_exif_chunk(Path(path)) if img.format == "PNG" else None)
        if raw:
            exif_all = Image.Exif()
            exif_all.load(raw)
        else:
            exif_all = Image.Exif() if img.format == "PNG" else img.getexif()
    return exif_all, size


def exif_focal_px(path: Path, width_px: int) -> float | None:
    """Focal in pixels of an image ``width_px`` wide from EXIF FocalLengthIn35mmFilm (diagonal crop factor, like
    the ingest node), None when absent or unreadable."""
    try:
        exif_all, (stored_w, stored_h) = _read_exif(path)
        f35 = exif_all.get_ifd(0x8769).get(0xA405)
    except Exception:
        return None
    if not f35 or stored_w <= 0:
        return None
    # The features may be computed on a resized copy: scale the stored image's focal to ``width_px``.
    return cam.focal_px_from_35mm(float(f35), stored_w, stored_h) * width_px / stored_w


def extract_all(
    paths: list[Path], max_features: int, max_side_px: int | None, workers: int = 2, show_progress: bool = True
) -> list[tuple[Features, np.ndarray]]:
    """Features and keypoint colours (N, 3) RGB u8 of every image (threads; OpenCV releases the GIL)."""

    def job(p: Path) -> tuple[Features, np.ndarray]:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise UserError(f"cannot read image {p}")
        feats = extract_features(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), max_features, max_side_px)
        ij = np.clip(np.round(feats.keypoints_px).astype(int), 0, [bgr.shape[1] - 1, bgr.shape[0] - 1])
        colors = bgr[ij[:, 1], ij[:, 0], ::-1].copy()
        return feats, colors

    # One OpenCV thread per worker: the images run in parallel already (OpenCV's own threads on top only
    # oversubscribe the cores).
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(max(1, workers)) as pool:
            it = pool.map(job, paths)
            bar = tqdm(it, total=len(paths), desc="features", unit="img", disable=not show_progress, file=sys.stderr)
            return list(bar)
    finally:
        cv2.setNumThreads(before)


def exif_gps_position(path: Path) -> GeoPoint | None:
    """EXIF GPS position of an image (``constructaide.geo.exif_gps``), None when absent or unreadable."""
    try:
        return exif_gps(_read_exif(path)[0])
    except Exception:
        return None


def exif_capture_time_ns(path: Path) -> int:
    """EXIF DateTimeOriginal as nanoseconds (with OffsetTimeOriginal when present, else read as UTC: only the
    order of the photos matters here), 0 when absent or unreadable."""
    import datetime as dt

    try:
        ifd = _read_exif(path)[0].get_ifd(0x8769)
        text, offset = ifd.get(0x9003), ifd.get(0x9011)
        when = dt.datetime.strptime(str(text).strip(), "%Y:%m:%d %H:%M:%S")
        tz = dt.UTC
        if offset:
            sign = -1 if str(offset).startswith("-") else 1
            hh, mm = str(offset).lstrip("+-").split(":")
            tz = dt.timezone(sign * dt.timedelta(hours=int(hh), minutes=int(mm)))
        return int(when.replace(tzinfo=tz).timestamp() * 1e9)
    except Exception:
        return 0


def reconstruction_to_colmap(recon: Reconstruction) -> ColmapModel:
    """Registered images and triangulated points as a COLMAP model (every keypoint written as a 2D point)."""
    pts, cols, *_ = recon.sparse_arrays()
    ok = np.nonzero(np.all(np.isfinite(recon.points), axis=1))[0]
    remap = -np.ones(len(recon.points), int)
    remap[ok] = np.arange(len(ok))
    images = []
    err_sum = np.zeros(len(pts))
    err_n = np.zeros(len(pts))
    for i, im in enumerate(recon.images):
        if not im.registered:
            continue
        t = recon.feature_track[i]
        p3 = np.where(t >= 0, remap[np.maximum(t, 0)], -1)
        images.append(ColmapImage(im.name, im.camera, im.pose, im.features.keypoints_px, p3))
        sel = p3 >= 0
        if sel.any():
            proj, _ = cam.project_points(im.camera, cam.invert_rigid(im.pose), pts[p3[sel]])
            e = np.linalg.norm(proj - im.features.keypoints_px[sel], axis=1)
            np.add.at(err_sum, p3[sel], np.nan_to_num(e, nan=0.0))
            np.add.at(err_n, p3[sel], 1)
    return ColmapModel(images, pts, cols, err_sum / np.maximum(err_n, 1))


def image_report(recon: Reconstruction) -> list[dict]:
    out = []
    for im in recon.images:
        d: dict = {"image": im.name, "status": im.status}
        if im.camera_id is not None:
            d["camera_id"] = im.camera_id
        d["method"] = im.method
        d["message"] = im.message
        if im.registered:
            d.update(
                f_px=im.camera.f_px,
                fy_over_fx=im.camera.fy_over_fx,
                cx_px=im.camera.cx_px,
                cy_px=im.camera.cy_px,
                k1=im.camera.k1,
                k2=im.camera.k2,
                num_inliers=im.num_inliers,
                rms_px=None if not math.isfinite(im.rms_px) else im.rms_px,
            )
            if im.anchor is not None:
                d["anchor_residuals_px"] = [float(r) for r in im.anchor.residuals_px]
                d["anchor_flagged_clicks"] = [int(k) for k in np.nonzero(im.anchor.outlier_mask)[0]]
        else:
            d["num_matched_tracks"] = im.num_matched_tracks
        if math.isfinite(im.centre_sigma_m):
            d["centre_sigma"] = im.centre_sigma_m
        if math.isfinite(im.gps_residual_m):
            d["gps_residual_m"] = im.gps_residual_m
        out.append(d)
    return out


def pair_consistency(recon: Reconstruction, cfg: MapperConfig) -> dict:
    """Loop consistency of the result: for every verified pair of registered images, the fraction of its matches
    within 2 % of the width of their epipolar lines under the final poses (a loop that did not close leaves the
    pairs across the seam inconsistent). Returns the pair count, the median and the worst fraction, and the pairs
    below 0.5 (image names and fraction)."""
    reg = set(recon.registered_indices())
    fracs: list[tuple[float, str, str]] = []
    for (a, b), g in recon.pairs.items():
        if a not in reg or b not in reg:
            continue
        ia, ib = recon.images[a], recon.images[b]
        xa = cam.pixels_to_normalized(ia.camera, ia.features.keypoints_px[g.matches[:, 0]].astype(np.float64))
        xb = cam.pixels_to_normalized(ib.camera, ib.features.keypoints_px[g.matches[:, 1]].astype(np.float64))
        thr = 2 * cfg.pnp_inlier_frac * ib.width_px
        ok, n = epipolar_agreement(xa, xb, cam.invert_rigid(ib.pose) @ ia.pose, ib.camera.f_px, thr)
        if n:
            fracs.append((ok / n, ia.name, ib.name))
    if not fracs:
        return {"pairs": 0}
    vals = np.array([f for f, _, _ in fracs])
    bad = sorted((f, a, b) for f, a, b in fracs if f < 0.5)
    return {
        "pairs": len(fracs),
        "median": float(np.median(vals)),
        "worst": float(vals.min()),
        "inconsistent": [{"images": [a, b], "fraction": round(f, 3)} for f, a, b in bad[:20]],
    }


def load_bim_lookup(
    bim_paths: tuple[Path, ...], tz: str = "UTC", terrain_height_m: float | None = None
) -> MeshDepthLookup:
    """The IFC file(s) as the register node's BIM view (the schedule's standing elements at a time, the terrain
    plane at ``terrain_height_m``), read as the ingest node reads them. UserError on a file that cannot be used."""
    try:
        site_model = load_site_model(bim_paths, tz=tz)
        return BimMeshes.from_site_model(site_model, terrain_height_m).depth_lookup()
    except ValueError as e:  # IfcLoadError, ScheduleError, a model without triangles
        raise UserError(f"--bim: {e}") from e


def _gray(path: Path) -> np.ndarray:
    """An image file as (H, W) uint8 grey. UserError when it cannot be read."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UserError(f"cannot read image {path}")
    return img


def _fixed_frames(recon: Reconstruction, paths: dict[str, Path], capture_time_ns: int) -> list[TextureFrame]:
    """Each fixed camera's registered frame nearest in time, read, as a texture source."""
    return [
        (_gray(paths[o.name]), o.camera, o.pose, o.capture_time_ns)
        for o in (recon.images[j] for j in nearest_fixed_frames(recon, capture_time_ns))
    ]


def retexture_phones(
    recon: Reconstruction, paths: dict[str, Path], lookup: MeshDepthLookup, cfg: MapperConfig
) -> set[str]:
    """Phone photos the texture found (method "model", no camera) refined again on the fixed cameras' frames at
    their final (polished) poses (:func:`~nodes.register.phonesearch.retexture`) and solved from the new model-point
    clicks, in place. Returns the names of those that moved."""
    moved: set[str] = set()
    for i, im in enumerate(recon.images):
        if not (im.registered and im.method == "model" and im.camera_id is None):
            continue
        frames = _fixed_frames(recon, paths, im.capture_time_ns)
        clicks = retexture(
            lookup, _gray(paths[im.name]), im.camera, im.pose, im.capture_time_ns, frames, cfg.model_search_clicks
        )
        if clicks is None:
            continue
        message = im.message
        try:
            register_anchor(recon, i, clicks, cfg)
        except DegenerateAnchors:
            continue
        im.method, im.message = "model", f"{message}; refined again on the fixed cameras' final poses"
        moved.add(im.name)
    return moved


def polish_reconstruction(
    recon: Reconstruction,
    paths: dict[str, Path],
    lookup: MeshDepthLookup,
    params: AlignParams | None = None,
    policy: PolishPolicy | None = None,
    progress: Callable[[int, int], None] | None = None,
    only: set[str] | None = None,
) -> dict[str, str]:
    """Polish the registered images' poses and intrinsics by the model outline, in place, as the register node
    polishes what it publishes (:func:`nodes.register.modelalign.polish_registration`: fixed cameras' frames, one
    polish per view, and anchored phone photos with their accepted clicks), in capture order (``only``: these
    images). Returns a note per image: how it was polished, or why not."""
    params = params or AlignParams()
    views: dict[str, ViewPolish] = {}
    order = sorted(
        (im for im in recon.images if im.registered and (only is None or im.name in only)),
        key=lambda im: (im.capture_time_ns, im.name),
    )
    notes: dict[str, str] = {}
    for k, im in enumerate(order):
        path = paths[im.name]

        def gray(path: Path = path) -> np.ndarray:
            return _gray(path)

        clicks = im.accepted_clicks if im.camera_id is None else None
        try:
            out = polish_registration(
                lookup, gray, im.camera, im.pose, im.capture_time_ns, im.camera_id, clicks, views, params, policy
            ) or Polished(None, None, "not polished (a phone photo without anchor clicks)")
        except (RuntimeError, ValueError) as e:  # no GL context, a degenerate render: the solved pose stands
            out = Polished(None, None, f"not polished: {e}")
        if out.world_from_camera is not None and out.intrinsics is not None:
            im.world_from_camera, im.intrinsics = out.world_from_camera, out.intrinsics
        notes[im.name] = out.note
        if progress is not None:
            progress(k + 1, len(order))
    return notes


def run_batch(
    images_dir: Path,
    anchors_path: Path,
    out_dir: Path,
    focal_px: float | None = None,
    cfg: MapperConfig | None = None,
    max_features: int = 4000,
    max_side_px: int | None = DEFAULT_MAX_SIDE_PX,
    bim_paths: tuple[Path, ...] = (),
    show_progress: bool = True,
    densify_params: DensifyParams | None = DEFAULT_DENSIFY,
    camera_folders: bool = False,
    tz: str = "UTC",
    terrain_height_m: float | None = None,
    polish_params: AlignParams | None = DEFAULT_POLISH,
) -> tuple[Reconstruction, dict]:
    """Register every image under ``images_dir``; write the COLMAP model and report.json to ``out_dir``.

    ``camera_folders``: the site layout (``constructaide.sitedir.camera_of``): the images of a first-level folder are
    the frames of one fixed camera, those under ``phone/`` or directly in ``images_dir`` phone photos; the mapper
    then treats them as the streaming node treats photos published with that camera id (its own frames' intrinsics
    and poses first, no relative pose at small parallax between its own frames).

    With ``densify_params`` (the default) the registered cloud is then densified by epipolar-guided matching
    (:func:`densify_reconstruction`; ``None`` skips it); its time is reported separately (``timings_secs``).

    ``bim_paths`` (IFC files; ``tz`` for schedule dates without an offset, ``terrain_height_m`` the ground level in
    the model frame): the registered poses are then polished by the model outline (:func:`polish_reconstruction`,
    before the densification; ``polish_params`` None skips it) and written so."""
    t0 = time.perf_counter()
    cfg = cfg or MapperConfig()
    anchors, file_focal, on_request = load_anchor_file(anchors_path)
    for b in bim_paths:
        if not Path(b).exists():
            raise UserError(f"--bim {b} does not exist")
    wants_model = (
        bool(polish_params)
        or (cfg.model_search and camera_folders)
        or cfg.min_outline_contrast is not None
        or cfg.phone_search
    )
    lookup = load_bim_lookup(tuple(bim_paths), tz, terrain_height_m) if bim_paths and wants_model else None
    named = find_images(images_dir)
    if not named:
        raise UserError(f"no images under {images_dir}")
    names = {n for n, _ in named}
    missing = [n for n in anchors if n not in names]
    if missing:
        raise UserError(f"anchor file names images not under {images_dir}: {', '.join(missing[:3])}")
    focal = focal_px if focal_px is not None else file_focal
    if focal is not None:
        cfg = msgspec.structs.replace(cfg, focal_px=focal)
    t_feat = time.perf_counter()
    feats = extract_all([p for _, p in named], max_features, max_side_px, cfg.workers, show_progress)
    recon = Reconstruction()
    for (name, path), (f, c) in zip(named, feats, strict=True):
        add_image(
            recon,
            name,
            f,
            c,
            exif_focal_px(path, f.width_px),
            exif_gps_position(path),
            camera_id=camera_of(name) if camera_folders else None,
            capture_time_ns=exif_capture_time_ns(path),
        )
    features_secs = time.perf_counter() - t_feat
    n_pairs = len(named) * (len(named) - 1) // 2
    bar_m = tqdm(total=n_pairs, desc="matching", unit="pair", disable=not show_progress, file=sys.stderr)
    bar_r = tqdm(total=len(named), desc="registering", unit="img", disable=not show_progress, file=sys.stderr)

    def prog(stage: str, n: int) -> None:
        bar_r.n = n
        bar_r.set_postfix_str(stage[-40:])
        bar_r.refresh()

    given = {n: c for n, c in anchors.items() if n not in on_request}
    answers = {n: c for n, c in anchors.items() if n in on_request}
    paths = dict(named)

    def by_model(i: int) -> tuple[Clicks | None, str]:
        im = recon.images[i]
        assert lookup is not None  # only passed with a lookup
        intr = cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))
        return model_anchor(lookup, _gray(paths[im.name]), intr, im.gps, im.capture_time_ns, cfg.model_search_clicks)

    def by_phone(i: int) -> tuple[Clicks | None, str]:
        im = recon.images[i]
        assert lookup is not None  # only passed with a lookup
        intr = cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))
        frames = _fixed_frames(recon, paths, im.capture_time_ns)
        return phone_anchor_in(recon, i, lookup, _gray(paths[im.name]), intr, cfg, frames)

    outline = None
    if lookup is not None and cfg.min_outline_contrast is not None:
        outline = OutlineCheck(lookup, cfg.min_outline_contrast)

    def check(i: int, intr: Intrinsics, world_from_camera: np.ndarray) -> str:
        im = recon.images[i]
        assert outline is not None  # only passed with one
        return outline.refusal(lambda: _gray(paths[im.name]), im.camera_id, im.capture_time_ns, intr, world_from_camera)

    reconstruct(
        recon,
        given,
        cfg,
        request_anchor=lambda name, reason, n: answers.pop(name, None),
        progress=prog,
        match_progress=lambda: bar_m.update(),
        by_model=by_model if lookup is not None else None,
        check=check if outline is not None else None,
        by_phone=by_phone if lookup is not None else None,
    )
    bar_m.close()
    bar_r.close()
    polish_notes: dict[str, str] = {}
    t_polish = time.perf_counter()
    retextured = lookup is not None and cfg.phone_search and cfg.phone_search_texture
    if lookup is not None and polish_params:
        bar_p = tqdm(total=0, desc="outline polish", unit="img", disable=not show_progress, file=sys.stderr)

        def pprog(done: int, total: int) -> None:
            bar_p.total, bar_p.n = total, done
            bar_p.refresh()

        try:
            polish_notes = polish_reconstruction(recon, dict(named), lookup, polish_params, progress=pprog)
            # phones found on the fixed frames' texture: again on their polished poses, then polished themselves
            moved = retexture_phones(recon, paths, lookup, cfg) if retextured else set()
            if moved:
                polish_notes |= polish_reconstruction(recon, dict(named), lookup, polish_params, only=moved)
        finally:
            lookup.close()  # the GL context and the model's buffers
            bar_p.close()
    elif lookup is not None:
        try:
            if retextured:
                retexture_phones(recon, paths, lookup, cfg)
        finally:
            lookup.close()
    polish_secs = time.perf_counter() - t_polish
    dense_stats = None
    if densify_params is not None:
        bar_d = tqdm(total=0, desc="densify", unit="pair", disable=not show_progress, file=sys.stderr)

        def dprog(done: int, total: int) -> None:
            bar_d.total, bar_d.n = total, done
            bar_d.refresh()

        dense_stats = densify_reconstruction(recon, densify_params, None, dprog)  # the images' EXIF times
        bar_d.close()
    out_dir = Path(out_dir)
    write_text_model(reconstruction_to_colmap(recon), out_dir)
    registered = [im.name for im in recon.images if im.registered]
    report = {
        "images_dir": str(images_dir),
        "anchors": str(anchors_path),
        "bim": [str(b) for b in bim_paths],
        "focal_prior_px": focal,
        "camera_folders": camera_folders,
        "num_images": len(recon.images),
        "num_registered": len(registered),
        "num_points": int(np.sum(np.all(np.isfinite(recon.points), axis=1))),
        "principal_points_refined": cfg.refine_principal_point,
        "anchors_released": recon.anchors_released,
        "anchor_release_score": (recon.anchor_release_score if math.isfinite(recon.anchor_release_score) else None),
        "accuracy_anchors": recon.accuracy_anchors,
        "registered": registered,
        "unregistered": [
            {"image": im.name, "status": im.status, "reason": im.message} for im in recon.images if not im.registered
        ],
        "needs_anchor": [{"image": n, "reason": r, "num_matched_tracks": c} for n, r, c in recon.needs_anchor],
        "images": [
            {**d, "polish": polish_notes[d["image"]]} if d["image"] in polish_notes else d for d in image_report(recon)
        ],
        "densify": dense_stats,
        "pair_consistency": pair_consistency(recon, cfg),
        "timings_secs": {
            "features": features_secs,
            **recon.timings_secs,
            "outline_polish": polish_secs,
            "total": time.perf_counter() - t0,
        },
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    return recon, report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="constructaide register",
        description="Register a folder of photos in the BIM frame from anchor clicks (model-assisted SfM, batch).",
    )
    ap.add_argument("--images", required=True, type=Path, help="folder of photos (searched recursively)")
    ap.add_argument("--anchors", required=True, type=Path, help="anchor clicks JSON file")
    ap.add_argument("--out", required=True, type=Path, help="output folder for the COLMAP text model + report.json")
    ap.add_argument(
        "--bim",
        action="append",
        default=[],
        type=Path,
        help="IFC model file(s) in the anchor clicks' frame: the registered poses are polished by the model's outlines "
        "(fixed cameras' frames with --camera-folders, and anchored photos with their clicks), as the streaming "
        "node polishes what it publishes; with --camera-folders a fixed camera that would need clicks is first "
        "searched for by the model's outlines around its EXIF GPS position (the IFC's site reference places it)",
    )
    ap.add_argument("--tz", default="UTC", help="time zone of schedule dates without an offset (with --bim)")
    ap.add_argument(
        "--terrain-height-m", type=float, default=None, help="ground level in the model frame (with --bim; z up)"
    )
    ap.add_argument("--no-outline-polish", action="store_true", help="with --bim: keep the poses as solved")
    ap.add_argument(
        "--no-model-search", action="store_true", help="with --bim: ask for every fixed camera's clicks (no search)"
    )
    ap.add_argument(
        "--phone-search",
        action="store_true",
        help="with --bim: search a phone photo by the model before asking for its clicks (experimental)",
    )
    ap.add_argument("--focal-px", type=float, default=None, help="focal prior in pixels for every image")
    ap.add_argument(
        "--max-side",
        type=int,
        default=DEFAULT_MAX_SIDE_PX,
        help=f"longest side for feature detection (px; default {DEFAULT_MAX_SIDE_PX}, COLMAP's max_image_size)",
    )
    ap.add_argument("--max-features", type=int, default=4000, help="SIFT features kept per image (strongest)")
    ap.add_argument("--refine-principal-point", action="store_true", help="optimise each image's principal point")
    anchor_mode = ap.add_mutually_exclusive_group()
    anchor_mode.add_argument(
        "--free-anchors", action="store_true", help="let anchor poses move in every bundle adjustment"
    )
    anchor_mode.add_argument(
        "--fixed-anchors",
        action="store_true",
        help="hold anchor poses fixed to the end (the paper; default: released in a final adjustment when the "
        "data support it)",
    )
    ap.add_argument(
        "--no-densify",
        action="store_true",
        help="skip densifying the cloud by epipolar-guided matching after registration",
    )
    ap.add_argument(
        "--target-centre-sigma",
        type=float,
        default=None,
        help="accuracy target in model units: while a camera centre's standard deviation exceeds it, the anchor "
        "file's clicks of the least certain image are used too (up to 4 images; the report's needs_anchor names "
        "the image to click next when the file has none)",
    )
    ap.add_argument(
        "--camera-folders",
        action="store_true",
        help="the site layout: each first-level folder holds one fixed camera's frames (folder name = camera id), "
        "phone/ and the top folder phone photos, as the streaming node gets them",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    if args.focal_px is not None and not (args.focal_px > 0):
        raise UserError("--focal-px must be positive")
    if args.target_centre_sigma is not None and not (args.target_centre_sigma > 0):
        raise UserError("--target-centre-sigma must be positive")
    if not args.camera_folders and looks_like_site_layout(args.images):
        print(
            f"note: {args.images} looks like a site's photos folder (one folder per fixed camera, phone/ for phones); "
            "--camera-folders treats each camera's frames as one camera, as the streaming node does",
            file=sys.stderr,
        )
    cfg = MapperConfig(
        refine_principal_point=args.refine_principal_point,
        fix_anchor_poses=not args.free_anchors,
        release_anchors=not args.fixed_anchors,
        target_centre_sigma=args.target_centre_sigma,
        model_search=not args.no_model_search,
        phone_search=args.phone_search,
    )
    _, report = run_batch(
        args.images,
        args.anchors,
        args.out,
        focal_px=args.focal_px,
        cfg=cfg,
        max_features=args.max_features,
        max_side_px=args.max_side,
        bim_paths=tuple(args.bim),
        show_progress=not args.quiet,
        densify_params=None if args.no_densify else DEFAULT_DENSIFY,
        camera_folders=args.camera_folders,
        tz=args.tz,
        terrain_height_m=args.terrain_height_m,
        polish_params=None if args.no_outline_polish else DEFAULT_POLISH,
    )
    print(
        f"registered {report['num_registered']}/{report['num_images']} images, {report['num_points']} points "
        f"in {report['timings_secs']['total']:.1f} s -> {args.out}"
    )
    by_model = [d["image"] for d in report["images"] if d.get("method") == "model"]
    if by_model:
        print(f"  anchored by the model's outlines, no clicks: {', '.join(by_model)}")
    sigmas = [d["centre_sigma"] for d in report["images"] if "centre_sigma" in d]
    if sigmas:
        print(
            f"  camera centres known to {statistics.median(sigmas):.3g} model units (median standard deviation over "
            f"{len(sigmas)} images, from the features and clicks)"
        )
    for u in report["unregistered"]:
        print(f"  unregistered {u['image']}: {u['reason']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
