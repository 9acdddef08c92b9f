"""Fixed cameras found by the model's outlines alone (nodes/register/modelsearch.py): seeded box scenes with
clutter, the synthetic site's frames through the search, the streaming registrar and the batch mapper. Truth is
read by the tests only (they are the scoring)."""

from __future__ import annotations

from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest

from constructaide import camera as cam
from constructaide.modelview import GROUND_INDEX, ModelView
from nodes.register.modelsearch import ModelAnchors, search_pose, virtual_clicks
from schemas.messages import GeoPoint

W, H, F = 640, 360, 560.0


def _box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])], float)
    f = np.array(
        [
            [0, 2, 1],
            [1, 2, 3],
            [4, 5, 6],
            [5, 7, 6],
            [0, 1, 4],
            [1, 5, 4],
            [2, 6, 3],
            [3, 6, 7],
            [0, 4, 2],
            [2, 4, 6],
            [1, 3, 5],
            [3, 7, 5],
        ]  # fmt: skip
    )
    return v, f


def _scene(rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A frame building: a slab per storey on columns, a core, random sizes (m)."""
    sx, sy = rng.uniform(12, 20), rng.uniform(8, 14)
    meshes = {}
    for k in range(int(rng.integers(2, 4))):
        z = 3.2 * k
        meshes[f"slab{k}"] = _box(np.array([0, 0, z + 2.9]), np.array([sx, sy, z + 3.2]))
        for i, x in enumerate(np.linspace(0, sx - 0.4, 4)):
            for j, y in enumerate((0.0, sy - 0.4)):
                meshes[f"col{k}{i}{j}"] = _box(np.array([x, y, z]), np.array([x + 0.4, y + 0.4, z + 2.9]))
    meshes["core"] = _box(np.array([sx * 0.4, sy * 0.3, 0]), np.array([sx * 0.6, sy * 0.7, 3.2 * 2]))
    return meshes


def _photo(view: ModelView, wfc: np.ndarray, rng: np.random.Generator, with_model: bool = True) -> np.ndarray:
    """A grey photo: the model's faces shaded (per element a tone), ground and sky, clutter strokes on them."""
    intr = cam.centered_intrinsics(W, H, F)
    res = view.raster(intr, wfc, None if with_model else set(), 0.0)
    ids = res.ids.astype(np.int64)
    element = (ids > 0) & (ids != GROUND_INDEX)
    tone = rng.uniform(60, 190, view.scene.num_elements + 1)
    img = np.where(element, 40 + 170 * res.shade + 0.2 * tone[np.where(element, ids, 0)], 0.0)
    img = np.where(ids == GROUND_INDEX, 110.0, np.where(ids == 0, 215.0, img))
    clutter = np.zeros((H, W), np.uint8)
    for _ in range(60):
        p = rng.uniform([0, 0], [W, H]).astype(int)
        q = p + rng.normal(0, 25, 2).astype(int)
        cv2.line(clutter, tuple(int(v) for v in p), tuple(int(v) for v in q), int(rng.integers(60, 255)), 1)
    img = np.where(~element & (clutter > 0), clutter, img)
    img = img + rng.normal(0, 4, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _true_camera(rng: np.random.Generator, target: np.ndarray) -> np.ndarray:
    ang = rng.uniform(0, 2 * np.pi)
    dist = rng.uniform(28, 38)
    centre = target + np.array([dist * np.cos(ang), dist * np.sin(ang), 0.0])
    centre[2] = rng.uniform(7, 12)
    aim = target + np.r_[rng.normal(0, 2.0, 2), rng.normal(0, 1.0)]
    return cam.look_at(centre, aim)


def _error_pct(wfc_a: np.ndarray, intr_a, wfc_b: np.ndarray, intr_b, pts: np.ndarray) -> float:  # noqa: ANN001
    """Mean distance between two cameras' pixels of the points (N, 3), % of the width."""
    pa, _ = cam.project_points(intr_a, cam.invert_rigid(wfc_a), pts)
    pb, _ = cam.project_points(intr_b, cam.invert_rigid(wfc_b), pts)
    return 100.0 * float(np.mean(np.linalg.norm(pa - pb, axis=1))) / intr_b.width_px


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_search_finds_a_fixed_camera_from_gps_and_the_model(seed: int) -> None:
    """A camera 3-4 m from where its GPS says, its focal prior 3 % off, turned up to ~5 deg from the model's middle:
    found within 0.5 % of the width (the issue's bar); the same search on a photo without the building refuses."""
    rng = np.random.default_rng(seed)
    meshes = _scene(rng)
    view = ModelView(meshes)
    try:
        allv = np.concatenate([v for v, _ in meshes.values()])
        lo, hi = allv.min(axis=0), allv.max(axis=0)
        target = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] + 0.35 * (hi[2] - lo[2])])
        wfc = _true_camera(rng, target)
        gray = _photo(view, wfc, rng)
        off = rng.normal(0, 1, 2)
        gps_xy = wfc[:2, 3] + 3.5 * off / np.linalg.norm(off)
        prior = cam.centered_intrinsics(W, H, F * 1.03)
        res = search_pose(view, gray, prior, (float(gps_xy[0]), float(gps_xy[1])), target, None, 0.0)
        assert res.world_from_camera is not None and res.intrinsics is not None, res.reason
        err = _error_pct(res.world_from_camera, res.intrinsics, wfc, cam.centered_intrinsics(W, H, F), allv)
        assert err < 0.5, (err, res.reason)
        px, pts = virtual_clicks(view, res.intrinsics, res.world_from_camera, None, 0.0, 24)
        assert len(px) == 24
        spread = px.max(axis=0) - px.min(axis=0)
        assert spread[0] > 0.15 * W and spread[1] > 0.1 * H  # spread over the outline, not bunched

        bare = _photo(view, wfc, rng, with_model=False)
        refused = search_pose(view, bare, prior, (float(gps_xy[0]), float(gps_xy[1])), target, None, 0.0)
        assert refused.world_from_camera is None
        assert "over chance" in refused.reason or "margin" in refused.reason
    finally:
        view.close()


def test_model_anchors_policy() -> None:
    """Phones are not searched; a camera is searched once per retry interval; no GPS or no site reference says so."""

    class Lookup:
        site_gps = None

    anchors = ModelAnchors(retry_secs=3600.0)
    calls: list[int] = []

    def gray() -> np.ndarray:
        calls.append(1)
        return np.zeros((H, W), np.uint8)

    g = GeoPoint(lat_deg=51.0, lon_deg=5.0, alt_m=0.0)
    assert anchors.find(Lookup(), gray, F, g, None, 0) == (None, "a phone photo")  # type: ignore[arg-type]
    clicks, why = anchors.find(Lookup(), gray, F, g, "cam-a", 0)  # type: ignore[arg-type]
    assert clicks is None and "site reference" in why
    clicks, why = anchors.find(Lookup(), gray, F, g, "cam-a", int(1800e9))  # type: ignore[arg-type]
    assert clicks is None and "lately" in why
    clicks, why = anchors.find(Lookup(), gray, F, None, "cam-a", int(7200e9))  # type: ignore[arg-type]
    assert clicks is None and "GPS" in why
    assert len(calls) == 2  # the photo is decoded only when searched


def _site_lookup(site: Path):  # noqa: ANN202
    import tomllib

    from constructaide.bim.ifc import load_site_model
    from nodes.register.bimdepth import MeshDepthLookup
    from nodes.register.bimsite import BimMeshes

    doc = tomllib.loads((site / "site.toml").read_text())
    tz, ground = doc["site"]["tz"], doc["site"]["terrain_height_m"]
    bim = BimMeshes.from_site_model(load_site_model([site / doc["paths"]["ifc"]], tz=tz), ground)
    lookup = MeshDepthLookup(
        bim.meshes,
        elements_at=bim.refs_at(),
        ground_height_m=ground,
        site_gps=bim.gps,
        origin_offset_m=bim.origin_offset_m,
    )
    return lookup, tz


def _last_frame(site: Path, camera: str) -> str:
    return sorted(p.relative_to(site / "photos").as_posix() for p in (site / "photos" / camera).glob("*.jpg"))[-1]


@pytest.mark.parametrize("site_fixture", ["small_site", "small_site_seed7"])
def test_streaming_registrar_anchors_a_fixed_camera_by_the_model(site_fixture: str, request) -> None:  # noqa: ANN001
    """The synthetic site's south camera, its last frame pushed first with no clicks anywhere: the streaming
    registrar registers it by the model (method "model", no request) within 0.5 % of the width of the truth, and
    with the search off it asks for clicks as before."""
    from constructaide.photos import photo_from_file
    from constructaide.synth.truth import load_cameras, true_camera
    from nodes.register.config import MapperConfig
    from nodes.register.photo import FrameImage, PhotoInput
    from nodes.register.streaming import StreamConfig, StreamingRegistrar

    site: Path = request.getfixturevalue(site_fixture)
    lookup, tz = _site_lookup(site)
    rel = _last_frame(site, "cam-south")
    meta = photo_from_file(site / "photos" / rel, "cam-south", "test", tz)
    photo = PhotoInput(
        rel,
        FrameImage((site / "photos" / rel).read_bytes()),
        camera_id="cam-south",
        capture_time_ns=meta.capture_time_ns,
        focal_px=meta.focal_px,
        gps=meta.gps,
    )
    try:
        off = StreamingRegistrar(StreamConfig(mapper=MapperConfig(model_search=False)), depth_lookup=lookup)
        assert off.register(photo).needs_anchor is not None
        reg = StreamingRegistrar(StreamConfig(), depth_lookup=lookup)
        out = reg.register(photo)
        assert out.needs_anchor is None, out.registration.message
        r = out.registration
        assert (r.status, r.method) == ("anchor", "model")
        assert "model's outlines" in r.message
        cams = load_cameras(site)
        intr_t, wfc_t = true_camera(site, rel, cams)
        depth_m = lookup.depth_map(wfc_t, intr_t, meta.capture_time_ns)
        v, u = np.nonzero(depth_m[::8, ::8] > 0)
        px = np.c_[u * 8, v * 8].astype(float)
        xy = cam.pixels_to_normalized(msgspec.structs.replace(intr_t, k1=0.0, k2=0.0), px)
        pts = np.c_[xy, np.ones(len(xy))] * depth_m[v * 8, u * 8][:, None]
        pts = pts @ wfc_t[:3, :3].T + wfc_t[:3, 3]
        assert r.intrinsics is not None
        err = _error_pct(cam.pose_from_tuple(r.world_from_camera), r.intrinsics, wfc_t, intr_t, pts)
        assert err < 0.5, err
    finally:
        lookup.close()
