"""Registration benchmark: model-assisted SfM (``constructaide register``) vs. pycolmap on ground-truth sets.

Sets: Middlebury templeSparseRing (16 x 640x480), Strecha fountain-P11 (11 x 3072x2048; both methods detect
features at full resolution: our default --max-side 3200 and pycolmap's max_image_size 3200), and the synthetic
site when ``constructaide.synth`` provides it.

Anchor clicks are simulated from ground truth (see ``bench/_datasets.py``): for each anchor image, SIFT matches
with its nearest ground-truth view are triangulated with the ground-truth cameras; 12 of those points, spread
over the image, are clicked at their ground-truth projection + N(0, 1 px) noise. The anchor file holds clicks for
every image (a user answering every NeedsAnchor request), first the first image and its nearest ground-truth view;
the algorithm starts from the first and uses the others only when it asks for an anchor ("anchors used" counts
them). The file's ``focal_px`` is the ground-truth mean focal; pycolmap gets the same focal prior. Each run
draws its own click noise (seed = run number) and the table reports means over the draws: one draw's gauge
error (the model frame fixed by 24 noisy clicks) varies by a factor 2 between draws on fountain-P11.

Errors, per registered image, averaged (the paper's Table 2): angle between estimated and ground-truth viewing
directions (deg); camera-centre distance (model units, and % of the ground-truth camera-to-scene distance, scene
= centroid of the checkpoints); reprojection error of ground-truth 3D checkpoints (GT-triangulated feature points)
in % of the image width. pycolmap's model is aligned to ground truth by a similarity on camera centres (as the
paper aligned VSfM; row "pycolmap, GT similarity"), and, in a second row, by the similarity that maps its cameras of
the anchor file's first two images onto the poses our anchor solve gets from their clicks ("pycolmap, anchor
similarity": both methods then take their gauge from the same user input); ours is used as is (it is in the model
frame).

Timing: ours is timed with ``run_batch(densify_params=None)`` (registration only, like pycolmap's incremental
mapping); the densification that ``run_batch`` runs by default afterwards is timed separately on the same
reconstruction (``densify_reconstruction`` with the default parameters, as ``run_batch`` calls it) and reported in
its own column.

Run: ``python bench/registration.py [--quick] [--runs N]`` (--quick: temple only, one run; default 6 runs).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import statistics
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._datasets import (  # noqa: E402
    FOUNTAIN_DIR,
    TEMPLE_DIR,
    GtCamera,
    checkpoints,
    load_fountain,
    load_synth,
    load_temple,
    nearest_view,
    simulate_anchor_clicks,
    simulate_realistic_clicks,
    simulate_realistic_synth_clicks,
    simulate_synth_clicks,
    synth_checkpoints,
)
from bench._registration_report import PYCOLMAP_ANCHOR, PYCOLMAP_GT, base_notes, write_section  # noqa: E402
from constructaide import camera as cam  # noqa: E402
from nodes.register import mapper  # noqa: E402
from nodes.register import recon as rc  # noqa: E402
from nodes.register.batch import (  # noqa: E402
    DEFAULT_DENSIFY,
    DEFAULT_MAX_SIDE_PX,
    exif_focal_px,
    find_images,
    load_anchor_file,
    run_batch,
)
from nodes.register.config import MapperConfig  # noqa: E402
from nodes.register.densify import densify_reconstruction  # noqa: E402
from nodes.register.features import Features  # noqa: E402
from schemas.messages import Intrinsics  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


NO_POLISH = "no outline polish"
"""Variant label: the synthetic sites' IFC not given to ``run_batch`` (the poses as solved; an ablation)."""


class BimInput(NamedTuple):
    """What ``run_batch`` gets of a synthetic site's model (``--bim``, ``--tz``, ``--terrain-height-m``)."""

    paths: tuple[Path, ...]
    tz: str
    terrain_height_m: float | None


def write_anchor_file(
    cams: list[GtCamera], anchor_idx: list[int], path: Path, seed: int = 0, realistic: bool = False
) -> float:
    """Anchor file with clicks for ``anchor_idx`` (the first given up front, the others on request): a careful
    user's (12 GT-triangulated points, 1 px noise) or, ``realistic``, a person's (strong corners, 1.5 px noise, 1 in
    20 a gross mis-click). Returns the focal prior written (the GT mean focal)."""
    focal = float(np.mean([(c.K[0, 0] + c.K[1, 1]) / 2 for c in cams]))
    anchors = []
    for k, i in enumerate(anchor_idx):
        if realistic:
            px, world, _ = simulate_realistic_clicks(cams, i, seed=seed)
        else:
            px, world = simulate_anchor_clicks(cams, i, seed=seed)
        anchors.append(
            {
                "image": cams[i].name,
                "points": [{"pixel": p.tolist(), "world": w.tolist()} for p, w in zip(px, world, strict=True)],
                # Only the starting anchor is given up front; the others answer the algorithm's requests.
                "on_request": k > 0,
            }
        )
    path.write_text(json.dumps({"anchors": anchors, "focal_px": focal}))
    return focal


def write_synth_anchor_file(
    site: Path, cams: list[GtCamera], path: Path, seed: int = 0, answer: str = "careful"
) -> int:
    """Anchor file for the synthetic site: the first anchor of its anchors.json (the realistic user's clicks on the
    first frame of the first camera) given up front, then, unless ``answer`` is "none", clicks for every other
    photo flagged ``on_request`` (held back until the algorithm asks for them): a careful user's (visible corners,
    1 px noise, no mis-clicks) or a realistic one's (1.5 px, 1 in 20 a gross mis-click), click draw ``seed``.
    Returns how many photos have clicks."""
    doc = json.loads((site / "anchors.json").read_text())
    doc["anchors"] = doc["anchors"][:1]
    have = {a["image"] for a in doc["anchors"]}
    for c in cams if answer != "none" else []:
        if c.name in have:
            continue
        try:
            if answer == "realistic":
                px, world, _ = simulate_realistic_synth_clicks(site, c, seed=seed)
            else:
                px, world = simulate_synth_clicks(site, c, seed=seed)
        except ValueError:  # fewer than 4 clickable corners: a person could not anchor it either
            continue
        points = [{"pixel": p.tolist(), "world": w.tolist()} for p, w in zip(px, world, strict=True)]
        doc["anchors"].append({"image": c.name, "points": points, "on_request": True})
    path.write_text(json.dumps(doc))
    return len(doc["anchors"])


def evaluate(
    cams: list[GtCamera],
    est: dict[str, tuple[Intrinsics, np.ndarray]],
    X_check: np.ndarray,
    focal_priors: dict[str, float | None] | None = None,
    worst: list[tuple[float, str]] | None = None,
) -> dict[str, float]:
    """Mean errors over registered images; ``est`` maps image name -> (intrinsics, world_from_camera).
    'reproj_max_pct_width': the worst image's mean checkpoint reprojection; 'implausible': registered images with
    |k1| or |k2| above 1 or a focal more than 20 % off its prior (``focal_priors``, EXIF; None: unknown).
    ``worst``, when given, gets the five worst images' (mean checkpoint reprojection % of the width, name)."""
    centre = X_check.mean(0)
    ang, dist, dist_pct, reproj, reproj_med = [], [], [], [], []
    names: list[str] = []
    implausible = 0
    for c in cams:
        if c.name not in est:
            continue
        names.append(c.name)
        intr, T = est[c.name]
        T_gt = c.world_from_camera
        ang.append(cam.viewing_angle_deg(T, T_gt))
        d = float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))
        dist.append(d)
        dist_pct.append(100 * d / float(np.linalg.norm(T_gt[:3, 3] - centre)))
        px_gt, vis = c.visible(X_check)
        px_est, z_est = cam.project_points(intr, cam.invert_rigid(T), X_check[vis])
        e = np.linalg.norm(px_est - px_gt[vis], axis=1)
        e[~np.isfinite(e)] = c.width_px
        reproj.append(100 * float(np.mean(e)) / c.width_px)
        reproj_med.append(100 * float(np.median(e)) / c.width_px)
        f0 = (focal_priors or {}).get(c.name)
        bad_f = f0 is not None and abs(intr.f_px / f0 - 1) > 0.2
        implausible += int(abs(intr.k1) > 1 or abs(intr.k2) > 1 or bad_f)
    if worst is not None:
        worst.extend(sorted(zip(reproj, names, strict=True), reverse=True)[:5])
    aligned = align_to_gt(est, cams)
    sim_dist = [
        float(np.linalg.norm(aligned[c.name][1][:3, 3] - c.world_from_camera[:3, 3])) for c in cams if c.name in aligned
    ]
    n = len(ang)
    nan = float("nan")
    return {
        "registered": n,
        "total": len(cams),
        "angle_deg": float(np.mean(ang)) if n else nan,
        "centre_dist": float(np.mean(dist)) if n else nan,
        "centre_dist_pct": float(np.mean(dist_pct)) if n else nan,
        "reproj_pct_width": float(np.mean(reproj)) if n else nan,
        "reproj_median_pct_width": float(np.mean(reproj_med)) if n else nan,
        "angle_deg_max": float(np.max(ang)) if n else nan,
        "reproj_max_pct_width": float(np.max(reproj)) if n else nan,
        "implausible": implausible,
        "centre_dist_after_similarity": float(np.mean(sim_dist)) if sim_dist else nan,
    }


def predicted_centre(report: dict, est: dict, cams: list[GtCamera]) -> dict[str, float]:
    """Our predicted camera-centre standard deviations (report ``centre_sigma``, model units) against the actual
    errors: mean predicted sigma over the images that have one, and the RMS of error / sigma (1 = calibrated;
    E|e|^2 = trace of the covariance). NaN when no image has a prediction."""
    gt = {c.name: c for c in cams}
    sig = {d["image"]: d["centre_sigma"] for d in report["images"] if "centre_sigma" in d and d["image"] in est}
    if not sig:
        return {"centre_sigma": float("nan"), "centre_z_rms": float("nan")}
    z = [float(np.linalg.norm(est[n][1][:3, 3] - gt[n].world_from_camera[:3, 3])) / s for n, s in sig.items() if s > 0]
    return {"centre_sigma": float(np.mean(list(sig.values()))), "centre_z_rms": float(np.sqrt(np.mean(np.square(z))))}


def run_ours(
    images_dir: Path,
    anchor_file: Path,
    out_dir: Path,
    max_side: int | None,
    cfg: MapperConfig,
    densify: bool = False,
    camera_folders: bool = False,
    bim: BimInput | None = None,
):
    """Our batch registration timed without densification; with ``densify`` the default densification is then run
    on the result and timed on its own (what the default ``run_batch`` does after registering); ``camera_folders``:
    the site layout (``register --camera-folders``). Returns (estimates, registration secs, report, densify secs or
    NaN)."""
    t0 = time.perf_counter()
    recon, report = run_batch(
        images_dir,
        anchor_file,
        out_dir,
        cfg=cfg,
        max_side_px=max_side,
        show_progress=False,
        densify_params=None,
        camera_folders=camera_folders,
        bim_paths=bim.paths if bim is not None else (),
        tz=bim.tz if bim is not None else "UTC",
        terrain_height_m=bim.terrain_height_m if bim is not None else None,
    )
    secs = time.perf_counter() - t0
    est = {im.name: (im.intrinsics, im.world_from_camera) for im in recon.images if im.registered}
    densify_secs = float("nan")
    if densify:
        t1 = time.perf_counter()
        densify_reconstruction(recon, DEFAULT_DENSIFY)  # the images' EXIF capture times, as run_batch read them
        densify_secs = time.perf_counter() - t1
    return est, secs, report, densify_secs


def anchor_solve_poses(
    images_dir: Path, anchor_file: Path, cams: list[GtCamera], cfg: MapperConfig, count: int = 2
) -> dict[str, np.ndarray]:
    """world_from_camera of the anchor file's first ``count`` images as our anchor solve gets them from their clicks
    (``mapper.register_anchor``: the file's focal prior, else the EXIF one, with the configured sigmas)."""
    clicks, file_focal, _ = load_anchor_file(anchor_file)
    if file_focal is not None:
        cfg = msgspec.structs.replace(cfg, focal_px=file_focal)
    size = {c.name: (c.width_px, c.height_px) for c in cams}
    out = {}
    for name in list(clicks)[:count]:
        w, h = size[name]
        recon = rc.Reconstruction()
        empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32), w, h)
        rc.add_image(recon, name, empty, focal_prior_px=exif_focal_px(Path(images_dir) / name, w))
        mapper.register_anchor(recon, 0, clicks[name], cfg)
        out[name] = recon.images[0].world_from_camera
    return out


def apply_similarity(
    est: dict[str, tuple[Intrinsics, np.ndarray]], s: float, R: np.ndarray, t: np.ndarray
) -> dict[str, tuple[Intrinsics, np.ndarray]]:
    """Poses ``world_from_camera`` mapped by the similarity x -> s R x + t (intrinsics unchanged)."""
    out = {}
    for name, (intr, T) in est.items():
        A = np.eye(4)
        A[:3, :3] = R @ T[:3, :3]
        A[:3, 3] = s * R @ T[:3, 3] + t
        out[name] = (intr, A)
    return out


def align_to_anchor_poses(
    est: dict[str, tuple[Intrinsics, np.ndarray]], targets: dict[str, np.ndarray]
) -> dict[str, tuple[Intrinsics, np.ndarray]]:
    """``est`` moved by the similarity that maps its cameras of the ``targets`` images (two) onto those poses: scale
    from their centres' distance, rotation the chordal mean of the two cameras' rotation changes, translation the
    mean of the centres'. Empty when ``est`` lacks one of them."""
    names = [n for n in targets if n in est]
    if len(names) < 2:
        return {}
    src = [est[n][1] for n in names]
    dst = [targets[n] for n in names]
    d_src = np.linalg.norm(src[0][:3, 3] - src[1][:3, 3])
    if d_src <= 0:
        return {}
    s = float(np.linalg.norm(dst[0][:3, 3] - dst[1][:3, 3]) / d_src)
    M = sum(b[:3, :3] @ a[:3, :3].T for a, b in zip(src, dst, strict=True))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    t = np.mean([b[:3, 3] - s * R @ a[:3, 3] for a, b in zip(src, dst, strict=True)], axis=0)
    return apply_similarity(est, s, R, t)


def run_pycolmap(images_dir: Path, work: Path, focal_px: float | None, max_side: int | None, width: int, height: int):
    import pycolmap

    t0 = time.perf_counter()
    db = work / "database.db"
    if db.exists():
        db.unlink()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    if focal_px is not None:
        reader.camera_params = f"{focal_px},{width / 2},{height / 2},0"
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = os.cpu_count() or 2
    ext.max_image_size = max_side if max_side else max(width, height)
    ext.use_gpu = False
    names = [n for n, _ in find_images(images_dir)]
    pycolmap.extract_features(
        db,
        images_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader,
        extraction_options=ext,
        device=pycolmap.Device.cpu,
    )
    match = pycolmap.FeatureMatchingOptions()
    match.use_gpu = False
    match.num_threads = os.cpu_count() or 2
    pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = os.cpu_count() or 2
    (work / "sparse").mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(db, images_dir, work / "sparse", options=opts)
    secs = time.perf_counter() - t0
    if not recs:
        return {}, secs
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    est = {}
    for img in rec.images.values():
        if hasattr(img, "has_pose") and not img.has_pose:
            continue
        T = np.eye(4)
        T[:3] = img.cam_from_world().matrix()
        c = rec.cameras[img.camera_id]
        p = list(c.params)
        f, cx, cy = p[0], p[1] - 0.5, p[2] - 0.5
        k1 = p[3] if len(p) > 3 else 0.0
        intr = Intrinsics(width_px=c.width, height_px=c.height, f_px=f, cx_px=cx, cy_px=cy, k1=k1, k2=0.0)
        est[img.name] = (intr, cam.invert_rigid(T))
    return est, secs


def align_to_gt(est: dict[str, tuple[Intrinsics, np.ndarray]], cams: list[GtCamera]):
    """Similarity (on camera centres) mapping the estimate to ground truth; returns aligned poses."""
    common = [c for c in cams if c.name in est]
    if len(common) < 3:
        return {}
    src = np.array([est[c.name][1][:3, 3] for c in common])
    dst = np.array([c.world_from_camera[:3, 3] for c in common])
    s, R, t = cam.umeyama_similarity(src, dst)
    return apply_similarity(est, s, R, t)


def mean_over_draws(per_draw: list[dict]) -> dict:
    """Metrics of several click-noise draws: the mean of each figure (NaN-aware), 'centre_dist_min'/'_max' over the
    draws, the RMS of 'centre_z_rms' (equal image counts), and 'anchors_used' as 'a' or 'a-b'."""
    out: dict = {}
    for key in per_draw[0]:
        vals = [d[key] for d in per_draw]
        if key in ("anchors_used", "model_anchors"):
            lo, hi = min(vals), max(vals)
            out[key] = f"{lo}" if lo == hi else f"{lo}-{hi}"
        elif key == "centre_z_rms":
            v = [x for x in vals if x == x]
            out[key] = float(np.sqrt(np.mean(np.square(v)))) if v else float("nan")
        elif key in ("registered", "total"):
            out[key] = min(vals)
        else:
            v = [x for x in vals if x == x]
            out[key] = float(np.mean(v)) if v else float("nan")
    dists = [d["centre_dist"] for d in per_draw]
    out["centre_dist_min"], out["centre_dist_max"] = float(np.min(dists)), float(np.max(dists))
    out["draws"] = len(per_draw)
    return out


Writer = Callable[[Path, int], float | None]
"""``write(path, draw)`` writes one click draw's anchor file and returns its focal prior (None: EXIF)."""


def bench_set(
    name: str,
    cams: list[GtCamera],
    images_dir: Path,
    max_side: int | None,
    runs: int,
    cfgs: dict,
    protocols: dict[str, Writer],
    X_check: np.ndarray | None = None,
    pycolmap_runs: int = 3,
    first_draw: int = 0,
    camera_folders: bool = False,
    bim: BimInput | None = None,
):
    """Rows for one set: for each anchor protocol (who clicks what: ``protocols`` label -> writer) and variant
    (``cfgs``), ours over ``runs`` click-noise draws (run r: draw first_draw + r); pycolmap (no clicks) in the first
    ``pycolmap_runs`` runs. Errors are means over the draws, times medians over the runs. pycolmap's
    anchor-similarity row uses the poses our anchor solve gets from the clicks of the first protocol whose file has
    two or more anchors."""
    if X_check is None:
        # Evaluation fixture: the same checkpoints whatever size the methods detect features at.
        X_check = checkpoints(cams)
    priors = {c.name: exif_focal_px(c.path, c.width_px) for c in cams}
    runs_of = [(p, label) for p in protocols for label in cfgs]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # Runs interleaved (every protocol and variant, then pycolmap, run after run) so that a change of machine
        # load during the benchmark hits every method alike.
        times: dict = {k: [] for k in [*runs_of, "pycolmap"]}
        densify_times: list[float] = []
        per_draw: dict = {k: [] for k in [*runs_of, "pycolmap", "pycolmap_anchor"]}
        colmap_est: dict = {}
        for r in range(runs):
            draw = first_draw + r
            anchor_poses: dict = {}
            focal = None
            for p_label, write in protocols.items():
                anchor_file = tmp / f"anchors_{p_label.replace(' ', '_')}_{draw}.json"
                focal = write(anchor_file, draw)
                if not anchor_poses and len(load_anchor_file(anchor_file).clicks) >= 2:
                    anchor_poses = anchor_solve_poses(images_dir, anchor_file, cams, MapperConfig())
                for k, label in enumerate(cfgs):
                    out = tmp / f"ours_{p_label.replace(' ', '_')}_{k}_{r}"
                    first = not densify_times or len(densify_times) < r + 1
                    polished = bim if label != NO_POLISH else None
                    est, secs, report, dsecs = run_ours(
                        images_dir, anchor_file, out, max_side, cfgs[label], first, camera_folders, polished
                    )
                    times[(p_label, label)].append(secs)
                    if first:
                        densify_times.append(dsecs)
                    # a person's clicks; a fixed camera the model's outlines found is no person's work
                    anchored = [im for im in report["images"] if im["status"] == "anchor"]
                    n_anchor = sum(1 for im in anchored if im.get("method") != "model")
                    worst: list[tuple[float, str]] = []
                    m = {
                        **evaluate(cams, est, X_check, priors, worst),
                        **predicted_centre(report, est, cams),
                        "anchors_used": n_anchor,
                        "model_anchors": len(anchored) - n_anchor,
                    }
                    per_draw[(p_label, label)].append(m)
                    print(f"  draw {draw} {p_label} / {label}: {json.dumps(m)}", flush=True)
                    print("  worst (% of the width):", ", ".join(f"{n} {e:.2f}" for e, n in worst), flush=True)
                    if report["unregistered"]:
                        print("  unregistered:", [u["image"] for u in report["unregistered"]], flush=True)
            if r < pycolmap_runs:
                work = tmp / f"colmap_{r}"
                work.mkdir()
                colmap_est, secs = run_pycolmap(images_dir, work, focal, max_side, cams[0].width_px, cams[0].height_px)
                times["pycolmap"].append(secs)
                gt_aligned = align_to_gt(colmap_est, cams)
                per_draw["pycolmap"].append({**evaluate(cams, gt_aligned, X_check, priors), "anchors_used": 0})
            if anchor_poses and r < pycolmap_runs:
                aligned = align_to_anchor_poses(colmap_est, anchor_poses)
                per_draw["pycolmap_anchor"].append(
                    {**evaluate(cams, aligned, X_check, priors), "anchors_used": len(anchor_poses)}
                )
        for n, key in enumerate(runs_of):
            p_label, label = key
            method = f"ours ({p_label})" if label == "default" else f"ours ({p_label}; {label})"
            rows.append(
                {
                    "set": name,
                    "method": method,
                    **mean_over_draws(per_draw[key]),
                    "secs": statistics.median(times[key]),
                    "densify_secs": statistics.median(densify_times) if n == 0 else float("nan"),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
        for method, key in ((PYCOLMAP_GT, "pycolmap"), (PYCOLMAP_ANCHOR, "pycolmap_anchor")):
            if not per_draw[key]:
                continue
            rows.append(
                {
                    "set": name,
                    "method": method,
                    **mean_over_draws(per_draw[key]),
                    "centre_sigma": float("nan"),
                    "centre_z_rms": float("nan"),
                    "secs": statistics.median(times["pycolmap"]) if times["pycolmap"] else float("nan"),
                    "densify_secs": float("nan"),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def real_protocols(cams: list[GtCamera], which: tuple[str, ...]) -> dict[str, Writer]:
    """Anchor protocols of a real set: 'one anchor' (a file with exactly the first image's clicks, nothing on
    request), 'requests answered' (clicks for every image, the first and its nearest view first; only the first
    given up front), each by a careful user and, 'realistic ...', a person (corners, 1.5 px, mis-clicks)."""
    first = [0, nearest_view(cams, 0)]
    order = first + [i for i in range(len(cams)) if i not in first]
    out: dict[str, Writer] = {}
    for real in (False, True):
        tag = "realistic user, " if real else ""
        if "one" in which:
            out[f"{tag}one anchor"] = lambda path, seed, real=real: write_anchor_file(cams, [0], path, seed, real)
        if "answered" in which:
            out[f"{tag}requests answered"] = lambda path, seed, real=real: write_anchor_file(
                cams, order, path, seed, real
            )
    return out


def synth_rows(
    size: str,
    seed: int,
    runs: int,
    cfgs: dict,
    first_draw: int = 0,
    pycolmap_runs: int = 3,
    which: tuple[str, ...] = ("one", "answered", "realistic"),
) -> tuple[list[dict], str]:
    try:
        from constructaide.synth import ensure_site
    except Exception as e:
        return [], f"synthetic site skipped: constructaide.synth not available ({type(e).__name__}: {e})"
    site = ensure_site(size, seed, ROOT / ".cache" / "synth")
    cams = load_synth(site)
    X = synth_checkpoints(site, cams)
    protocols: dict[str, Writer] = {}
    for key, answer, label in (
        ("one", "none", "one anchor"),
        ("answered", "careful", "requests answered"),
        ("realistic", "realistic", "realistic user"),
    ):
        if key not in which:
            continue

        def write(path: Path, draw: int, answer: str = answer) -> float | None:
            write_synth_anchor_file(site, cams, path, seed=draw, answer=answer)
            return None

        protocols[label] = write
    name = f"synthetic {size} (seed {seed})"
    doc = tomllib.loads((site / "site.toml").read_text())
    bim = BimInput((site / doc["paths"]["ifc"],), doc["site"]["tz"], doc["site"].get("terrain_height_m"))
    rows = bench_set(name, cams, site / "photos", None, runs, cfgs, protocols, X, pycolmap_runs, first_draw, True, bim)
    return rows, synth_note(size, seed)


def synth_note(size: str, seed: int) -> str:
    return (
        f"synthetic {size} (seed {seed}): protocols 'one anchor' (the first anchor of the site's anchors.json, the "
        "realistic user's clicks on the first frame of the first fixed camera: visible element corners, 1.5 px "
        "noise, ~1 in 20 a gross mis-click; nothing on request), 'requests answered' (that anchor up front, then a "
        "careful user's clicks for any photo asked for: visible corners, 1 px noise, no mis-clicks) and 'realistic "
        "user' (answers by the realistic user). No focal in the anchor file: both methods start from the photos' "
        "EXIF 35 mm-equivalent focal. Checkpoints = ground-truth depth maps back-projected at 60 random pixels per "
        "photo that show a BIM element. The fixed cameras' photos add no triangulation baseline; cam-east is "
        "knocked half-way through the period and must be found and re-registered without clicks."
    )


EXTRA_VARIANTS = {
    # Only when named with --variants: fixed cameras not searched for by the model before a request (the rule
    # before 2026-12-07).
    "no model search": MapperConfig(model_search=False),
    "phone search": MapperConfig(phone_search=True),
    # Only when named with --variants: a phone's automatic pose not checked by the model's outlines, relative poses
    # at any parallax (the rules before 2026-12-07, afternoon).
    "no outline check": MapperConfig(min_outline_contrast=None, bootstrap_max_parallax_deg=180.0),
    # Only when named with --variants: the second anchor asked in collection order (the rule before
    # MapperConfig.anchor_request_min_shared_matches).
    "second anchor: collection order": MapperConfig(anchor_request_min_shared_matches=0),
}
SETS = ("temple", "fountain", "synthetic-small", "synthetic-small-7", "synthetic-default", "synthetic-default-7")
PROTOCOLS = ("one", "answered")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="temple only, one run")
    ap.add_argument(
        "--runs", type=int, default=None, help="runs = click-noise draws (default 6; pycolmap runs in at most 3)"
    )
    ap.add_argument("--synthetic-runs", type=int, default=3, help="runs on the small synthetic sites (default 3)")
    ap.add_argument(
        "--resume",
        default=None,
        help="stdout of an earlier run of the same command: sets whose rows it printed are taken from it",
    )
    ap.add_argument("--default-site-runs", type=int, default=1, help="runs on the 110-photo default sites (default 1)")
    ap.add_argument(
        "--skip-pycolmap-default",
        action="store_true",
        help="do not run pycolmap on the 110-photo default sites (about 55 min each on 2 cores); say so in the notes",
    )
    ap.add_argument("--first-draw", type=int, default=0, help="click-noise draw of the first run (default 0)")
    ap.add_argument("--sets", default=None, help=f"comma-separated subset of {','.join(SETS)} (default: all)")
    ap.add_argument(
        "--protocols",
        default=",".join(PROTOCOLS),
        help="'one' anchor and/or requests 'answered' (synthetic sites also 'realistic'; by default all three)",
    )
    ap.add_argument(
        "--variants",
        default=None,
        help="comma-separated parts of variant labels to run (default: 'default'; 'all' for the ablations)",
    )
    ap.add_argument(
        "--section", default=None, help="BENCHMARKS.md section for a non-standard run (default: the 'selected' one)"
    )
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    if args.runs is not None and args.runs < 1:
        ap.error("--runs must be >= 1")
    runs = args.runs or (1 if args.quick else 6)
    sets = ("temple",) if args.quick else SETS
    if args.sets:
        sets = tuple(x.strip() for x in args.sets.split(","))
        synth = re.compile(r"^synthetic-(tiny|small|default|large)(-\d+)?$")
        if unknown := [x for x in sets if x not in SETS and not synth.match(x)]:
            ap.error(f"unknown set(s) {', '.join(unknown)}; choose from {', '.join(SETS)} or synthetic-SIZE-SEED")
    protocols = tuple(x.strip() for x in args.protocols.split(",") if x.strip())
    all_cfgs = {
        "default": MapperConfig(),
        "paper: anchors fixed, anchor k1 = 0": MapperConfig(anchor_distortion=False, release_anchors=False),
        "release: square pixels": MapperConfig(release_aspect=False),
        "pp refined": MapperConfig(refine_principal_point=True),
        "pp refined, anchors free": MapperConfig(refine_principal_point=True, fix_anchor_poses=False),
        "accuracy target 5 mm": MapperConfig(target_centre_sigma=0.005),
        "no relative-pose bootstrap": MapperConfig(bootstrap=False),
        "no lens hold": MapperConfig(max_anchor_click_drift_px=None),
        NO_POLISH: MapperConfig(),
        **EXTRA_VARIANTS,
    }
    cfgs = {"default": all_cfgs["default"]}
    if args.variants == "all":
        cfgs = all_cfgs
    elif args.variants:
        wanted = [w.strip() for w in args.variants.split(",") if w.strip()]
        cfgs = {k: v for k, v in all_cfgs.items() if any(w in k for w in wanted)}
        if not cfgs:
            ap.error(f"no variant label contains any of {wanted}")
    rows: list[dict] = []
    notes = base_notes()
    first = args.first_draw
    earlier: dict[str, list[dict]] = {}
    if args.resume:
        for line in Path(args.resume).read_text().splitlines():
            if line.startswith('{"set"'):
                row = json.loads(line)
                earlier.setdefault(row["set"], []).append(row)

    def resumed(name: str) -> bool:
        if name not in earlier:
            return False
        rows.extend(earlier[name])
        notes.append(f"{name}: rows from an earlier run of the same command (--resume {args.resume}).")
        return True

    for key, name, root, loader, images, max_side in (
        ("temple", "templeSparseRing", TEMPLE_DIR, load_temple, TEMPLE_DIR, None),
        ("fountain", "fountain-P11", FOUNTAIN_DIR, load_fountain, FOUNTAIN_DIR / "images", DEFAULT_MAX_SIDE_PX),
    ):
        if key not in sets:
            continue
        if not root.exists():
            notes.append(f"{name} skipped: {root} absent")
            continue
        if resumed(name):
            continue
        cams = loader()
        rows += bench_set(name, cams, images, max_side, runs, cfgs, real_protocols(cams, protocols), first_draw=first)
    for set_name in sets:
        if not set_name.startswith("synthetic-"):
            continue
        parts = set_name.split("-")
        size, seed = parts[1], int(parts[2]) if len(parts) > 2 else 0
        n = args.default_site_runs if size == "default" else min(runs, args.synthetic_runs)
        if resumed(f"synthetic {size} (seed {seed})"):
            continue
        pyc = 1 if size == "default" else 3
        if args.skip_pycolmap_default and size == "default":
            pyc = 0
            notes.append(
                f"synthetic default (seed {seed}): pycolmap not run in this run (--skip-pycolmap-default: about 55 "
                "min here); its rows are from the earlier run named in the section 'registration (selected draws, "
                "sets or variants)' of 2026-12-03 08:18"
            )
        synth_which = protocols if args.protocols != ",".join(PROTOCOLS) else ("one", "answered", "realistic")
        srows, note = synth_rows(size, seed, n, cfgs, first, pycolmap_runs=pyc, which=synth_which)
        rows += srows
        if note:
            notes.append(note)
    if not args.no_write:
        if all(x.startswith("synthetic-") for x in sets):  # the synthetic sets run fewer draws (see above)
            runs = min(runs, args.synthetic_runs) if any("-default" not in x for x in sets) else args.default_site_runs
        cmd = shlex.join(["python", "bench/registration.py", *(argv if argv is not None else sys.argv[1:])])
        standard = not (args.sets or args.variants or args.first_draw or args.protocols != ",".join(PROTOCOLS))
        if standard:
            write_section(rows, notes, cmd, runs)
        else:
            # Selected draws / sets / variants go to their own section; the standard table stays as measured.
            draws = f"{args.first_draw}-{args.first_draw + runs - 1}"
            note = f"Same protocol as the 'registration' section (its notes apply); click draws {draws}."
            write_section(
                rows, [note], cmd, runs, title=args.section or "registration (selected draws, sets or variants)"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
