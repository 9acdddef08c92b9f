"""Build a synthetic site folder (see README.md in this package for the layout contract)."""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
from tqdm import tqdm

from constructaide.bimgeom import meshes_to_glb
from constructaide.camera import K_matrix
from constructaide.errors import UserError

from .building import design_building
from .cameras import fixed_camera_plans, phone_visit_plans
from .clicker import MIN_CLICKS, ModelCorners, click_points, photo_rng
from .config import ALT_M, LAT_DEG, LON_DEG, SITE_NAME, SIZES, TZ
from .ifcwrite import write_ifc
from .photo_io import write_jpeg, write_npz, write_png
from .render import Lighting, SiteRenderer, element_index_map
from .scene import clear_trees, dynamic_poses, dynamic_solids, make_layout, static_solids
from .schedule import hours_to_datetime, make_schedule
from .sun import sun_azimuth_elevation_deg, sun_direction_world
from .textures import make_textures, site_ground
from .truth import truth_rel

GENERATOR_VERSION = 10
"""Bump whenever outputs change; part of the ``ensure_site`` cache key."""

_MATERIAL_RGBA = {
    "concrete": (160, 160, 155, 255),
    "brick": (150, 65, 45, 255),
    "glass": (90, 120, 150, 160),
    "steel": (70, 90, 120, 255),
    "roof": (150, 70, 45, 255),
}


def _lighting(seed: int, day: int, when: dt.datetime) -> Lighting:
    rng = np.random.default_rng([seed, 77, day + 1000])
    cloudiness = float(rng.uniform(0.05, 0.95))
    az, el = sun_azimuth_elevation_deg(when, LAT_DEG, LON_DEG)
    strength = min(1.0, max(0.15, math.sin(math.radians(max(el, 1.0))) * 1.6))
    clear_z, grey_z = np.array([85.0, 135.0, 210.0]), np.array([175.0, 180.0, 188.0])
    clear_h, grey_h = np.array([190.0, 210.0, 235.0]), np.array([205.0, 208.0, 212.0])
    return Lighting(
        sun_dir_world=sun_direction_world(az, el),
        sun_intensity=float(4.0 * strength * (1.0 - 0.7 * cloudiness)),
        ambient=float(0.35 + 0.35 * cloudiness),
        sky_zenith=tuple(clear_z * (1 - cloudiness) + grey_z * cloudiness),
        sky_horizon=tuple(clear_h * (1 - cloudiness) + grey_h * cloudiness),
        exposure=float(rng.uniform(0.88, 1.12)),
        cloud_seed=int(rng.integers(0, 2**31)),
        cloudiness=cloudiness,
    )


FIXED_GPS_BIAS_M = (3.5, 4.5)  # a fixed camera's GPS fix is off by this much (a constant direction per camera)
FIXED_GPS_JITTER_M = 0.5  # plus a different offset within this radius per frame: 3-5 m in all


def _gps_error_m(seed: int, camera_id: str, i: int) -> np.ndarray:
    """Horizontal GPS error (3,) m of frame ``i`` of a fixed camera: a per-camera bias of 3.5-4.5 m plus up to
    0.5 m per frame (so 3-5 m), drawn from their own generators (the renders stay as they were)."""
    cam_rng = np.random.default_rng([seed, 300, sum(map(ord, camera_id))])
    a, r = cam_rng.uniform(0.0, 2.0 * math.pi), cam_rng.uniform(*FIXED_GPS_BIAS_M)
    frame_rng = np.random.default_rng([seed, 301, i])
    b, q = frame_rng.uniform(0.0, 2.0 * math.pi), FIXED_GPS_JITTER_M * math.sqrt(frame_rng.uniform())
    return np.array([r * math.cos(a) + q * math.cos(b), r * math.sin(a) + q * math.sin(b), 0.0])


def _iso(d: dt.datetime | None) -> str | None:
    return None if d is None else d.isoformat(timespec="seconds")


def build_site(out_dir: Path, seed: int = 0, size: str = "default", progress: bool = True) -> Path:
    """Render a complete site folder into ``out_dir`` (must not exist or be empty). Returns ``out_dir``."""
    if size not in SIZES:
        raise UserError(f"unknown site size {size!r}; choose one of {', '.join(SIZES)}")
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise UserError(f"{out_dir} exists and is not empty; choose a new --out directory")
    cfg = SIZES[size]
    out_dir.mkdir(parents=True, exist_ok=True)

    def rng(k: int) -> np.random.Generator:
        return np.random.default_rng([seed, k])

    building = design_building(cfg)
    schedule = make_schedule(building, cfg.days, rng(1))
    guids = write_ifc(building, schedule, out_dir / "model" / "building.ifc", seed)
    meshes = {guids[e.key]: (e.vertices_m, e.triangles()) for e in building.elements}
    colors = {guids[e.key]: _MATERIAL_RGBA[e.material] for e in building.elements}
    (out_dir / "model" / "building.glb").write_bytes(meshes_to_glb(meshes, colors))
    index = element_index_map(building)

    plans = fixed_camera_plans(building, cfg.cameras, cfg.days, cfg.fixed_resolution, rng(5))
    layout = clear_trees(make_layout(building), building, [p.world_from_camera[:3, 3] for p in plans if p.day == 0])
    textures = make_textures(rng(2), cfg.texture_px)
    textures["site_ground"] = site_ground(
        rng(3), cfg.ground_texture_px, layout.site_extent_m, layout.paths, layout.pads
    )
    renderer = SiteRenderer(
        building,
        index,
        static_solids(layout),
        dynamic_solids(layout, building.top_m),
        textures,
        layout.site_extent_m,
        rng(4),
    )
    plans += phone_visit_plans(building, layout, cfg.visits, cfg.days, cfg.phone_resolution, rng(6))
    plans.sort(key=lambda p: (p.local_time, p.rel_path))

    finish = {
        k: (None if w.actual_finish_h is None else hours_to_datetime(w.actual_finish_h))
        for k, w in schedule.windows.items()
    }
    cameras_json: dict[str, dict] = {}
    built_json: dict[str, list[str]] = {}
    anchors: list[dict] = []
    anchor_truth: dict[str, dict] = {}
    anchored: set[tuple] = set()
    corners = ModelCorners.from_meshes({index[e.key]: (e.vertices_m, e.triangles()) for e in building.elements})
    photos_dir, truth_dir = out_dir / "photos", out_dir / "truth"
    try:
        for i, plan in enumerate(tqdm(plans, desc=f"synth {size}", unit="photo", disable=not progress)):
            built = {k for k, t in finish.items() if t is not None and t <= plan.local_time}
            prng = np.random.default_rng([seed, 100, i])
            cam_xy = plan.world_from_camera[:2, 3]
            poses = dynamic_poses(layout, prng, plan.day, cam_xy)
            res = renderer.render(
                plan.intrinsics, plan.world_from_camera, built, poses, _lighting(seed, plan.day, plan.local_time), prng
            )
            intr = plan.intrinsics
            f_mm = intr.f_px * plan.sensor_width_mm / intr.width_px
            # 35 mm equivalent by the diagonal crop factor (36 x 24 mm frame), as cameras and exiftool do
            f35 = intr.f_px * math.hypot(36.0, 24.0) / math.hypot(intr.width_px, intr.height_px)
            gps_pos = plan.world_from_camera[:3, 3]
            if plan.camera_id is None:  # phone GPS is a few metres off
                gps_pos = gps_pos + np.array([*prng.normal(0.0, 3.0, 2), 0.0])
            else:  # so is a fixed camera's
                gps_pos = gps_pos + _gps_error_m(seed, plan.camera_id, i)
            write_jpeg(
                photos_dir / plan.rel_path,
                res.color,
                plan.local_time,
                f_mm,
                f35,
                gps_pos,
                "TimeLapse TL-4K" if plan.camera_id else "Phone X12",
            )
            write_png(truth_dir / truth_rel("ids", plan.rel_path), res.element_index)
            write_npz(truth_dir / truth_rel("depth", plan.rel_path), depth_m=res.depth_m)
            write_png(truth_dir / truth_rel("masks/static", plan.rel_path), res.static_mask.astype(np.uint8) * 255)
            write_png(truth_dir / truth_rel("masks/dynamic", plan.rel_path), res.dynamic_mask.astype(np.uint8) * 255)
            cameras_json[plan.rel_path] = {
                "K": K_matrix(intr).tolist(),
                "k1": intr.k1,
                "k2": intr.k2,
                "width": intr.width_px,
                "height": intr.height_px,
                "world_from_camera": plan.world_from_camera.tolist(),
                "capture_time_utc_ns": int(plan.local_time.timestamp()) * 1_000_000_000,
                "camera_id": plan.camera_id,
            }
            built_json[plan.rel_path] = sorted(guids[k] for k in built)
            # The user anchors the first usable photo of each fixed camera and of each phone visit (not a knocked
            # camera's new pose: nobody knows it was knocked), clicking visible corners (constructaide.synth.clicker).
            group = (plan.camera_id, plan.visit)
            if group not in anchored:
                px, world = corners.visible(intr, plan.world_from_camera, res.element_index, res.depth_m)
                if len(px) >= MIN_CLICKS:
                    clicks = click_points(px, world, photo_rng(seed, plan.rel_path), (intr.width_px, intr.height_px))
                    anchored.add(group)
                    anchors.append({"image": plan.rel_path, "points": clicks.anchor_points()})
                    anchor_truth[plan.rel_path] = {
                        "target_px": np.round(clicks.target_px, 4).tolist(),
                        "mis_clicked": clicks.mis_clicked.tolist(),
                        "miss_kinds": list(clicks.miss_kinds),
                        "n_clickable": clicks.n_clickable,
                    }
    finally:
        renderer.close()

    def dump(path: Path, obj: object) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(obj, indent=1, sort_keys=False) + "\n")

    dump(out_dir / "anchors.json", {"anchors": anchors, "focal_px": None})
    dump(truth_dir / "cameras.json", cameras_json)
    dump(truth_dir / "anchor_clicks.json", anchor_truth)
    dump(truth_dir / "element_index.json", {"0": None, **{str(index[e.key]): guids[e.key] for e in building.elements}})
    elements_json = {}
    for e in building.elements:
        w = schedule.windows[e.key]
        elements_json[guids[e.key]] = {
            "name": e.key,
            "index": index[e.key],
            "ifc_class": e.ifc_class,
            "storey": e.storey,
            "task": e.task,
            "planned_start": _iso(hours_to_datetime(w.planned_start_h)),
            "planned_finish": _iso(hours_to_datetime(w.planned_finish_h)),
            "actual_start": _iso(None if w.actual_start_h is None else hours_to_datetime(w.actual_start_h)),
            "actual_finish": _iso(finish[e.key]),
            "never_built": w.never_built,
            "deviation": w.deviation,
        }
    dump(truth_dir / "element_states.json", {"elements": elements_json, "photos": built_json})
    (out_dir / "site.toml").write_text(
        "# Synthetic construction site generated by constructaide.synth "
        f"(size={size}, seed={seed}, generator version {GENERATOR_VERSION}).\n"
        "# World frame: site-local metres, x east, y north, z up, ground at z = 0.\n"
        "[site]\n"
        f'name = "{SITE_NAME}"\n'
        f"lat_deg = {LAT_DEG}\n"
        f"lon_deg = {LON_DEG}\n"
        f"alt_m = {ALT_M}\n"
        f'tz = "{TZ}"\n'
        "terrain_height_m = 0.0\n"
        "\n[paths]\n"
        'ifc = "model/building.ifc"\n'
        'glb = "model/building.glb"\n'
        'photos = "photos"\n'
        'anchors = "anchors.json"\n'
    )
    return out_dir


def ensure_site(size: str, seed: int, cache_dir: Path) -> Path:
    """Return a cached site folder for (size, seed, GENERATOR_VERSION), building it first if missing.

    Builds into a temporary sibling directory and renames it into place (atomic); a lock file serialises
    concurrent callers so the site is rendered once.
    """
    if size not in SIZES:
        raise UserError(f"unknown site size {size!r}; choose one of {', '.join(SIZES)}")
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    key = f"site-{size}-seed{seed}-v{GENERATOR_VERSION}"
    final = cache_dir / key
    if (final / "site.toml").is_file():
        return final
    with open(cache_dir / f".{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (final / "site.toml").is_file():
            return final
        for stale in cache_dir.glob(f".{key}.tmp-*"):  # left by a killed build; we hold the lock
            shutil.rmtree(stale, ignore_errors=True)
        tmp = cache_dir / f".{key}.tmp-{os.getpid()}"
        try:
            build_site(tmp, seed=seed, size=size, progress=size not in ("tiny", "small"))
            if final.exists():
                shutil.rmtree(final)
            os.rename(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
    return final
