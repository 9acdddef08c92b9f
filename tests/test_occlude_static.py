"""Model depth maps and static occlusion masks on a seeded synthetic facade / fence / ground scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from occlude_scenes import _box, iou, static_scene

from constructaide.camera import centered_intrinsics, invert_rigid, look_at, project_points, scaled_intrinsics
from constructaide.modelview import ModelMaps, ModelView
from nodes.occlude.stacks import working_size
from nodes.occlude.static import (
    StaticParams,
    classify_points,
    estimate_point_normals,
    estimate_terrain_height,
    harmonic_labels,
    propagate_labels,
    static_mask,
)


@pytest.fixture(scope="module")
def scene():
    return static_scene(11)


def _small(img: np.ndarray, width: int = 640) -> np.ndarray:
    w, h, _ = working_size(img.shape[1], img.shape[0], width)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("k1", [0.0, -0.12])
def test_model_depth_matches_projection(k1: float) -> None:
    intr = centered_intrinsics(1280, 720, 1000.0, k1=k1, k2=0.02 if k1 else 0.0)
    wfc = look_at((3.0, -15.0, 4.0), (0.0, 0.0, 2.0))
    r = ModelView({"wall": _box((12.0, 0.5, 8.0), (0.0, 0.25, 2.0))})
    maps = r.maps(intr, wfc, 640, 360)
    r.close()
    small = scaled_intrinsics(intr, 640, 360)
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-5, 5, 50), np.zeros(50), rng.uniform(-1.5, 5.5, 50)], axis=1)
    px, z = project_points(small, invert_rigid(wfc), pts)
    ui, vi = np.round(px).astype(int).T
    inside = (ui > 1) & (ui < 638) & (vi > 1) & (vi < 358)
    assert inside.sum() > 30
    assert np.allclose(maps.depth_m[vi[inside], ui[inside]], z[inside], rtol=0.01)
    assert np.allclose(maps.point_in_world_m[vi[inside], ui[inside]], pts[inside], atol=0.08)
    n = maps.normal_in_world[vi[inside], ui[inside]]
    assert np.all(n[:, 1] < -0.99)  # the face y = 0 seen from -y: normal towards the camera
    assert not np.isfinite(maps.depth_m[0, 0]) or maps.depth_m[0, 0] > 0  # sky pixels are inf


def test_point_normals_from_pca() -> None:
    rng = np.random.default_rng(1)
    plane = np.stack([rng.uniform(0, 5, 400), rng.uniform(0, 5, 400), rng.normal(0, 0.005, 400)], axis=1)
    normals, flatness = estimate_point_normals(plane)
    assert np.all(np.abs(normals[:, 2]) > 0.98)
    assert np.all(flatness < 0.01)
    blob = rng.normal(0, 1, (300, 3))
    _, flat_blob = estimate_point_normals(blob)
    assert np.median(flat_blob) > 0.1


def test_classify_depth_and_normal_rules() -> None:
    h, w = 10, 10
    depth = np.full((h, w), 10.0, np.float32)
    pts_world = np.zeros((h, w, 3), np.float32)
    pts_world[..., 2] = 10.0  # camera at origin looking +z in world = camera frame
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = -1.0
    maps = ModelMaps(depth, normals, pts_world)
    P = np.array([[0, 0, 9.5], [0, 0, 9.9], [0, 0, 10.5], [0, 0, 9.95], [0, 0, 9.9]], np.float64)
    px = np.full((5, 2), 5.0)
    n_pts = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 1, 0]], np.float32)
    flat = np.array([0.0, 0.0, 0.0, 0.0, 0.2], np.float32)  # the last normal is not trusted
    judged, occ = classify_points(P, px, np.zeros(3), maps, n_pts, flat, StaticParams())
    assert judged.all()
    assert occ.tolist() == [True, False, False, True, False]


def test_static_mask_fence_and_ground(scene) -> None:
    small = _small(scene.image)
    r = ModelView(scene.model_meshes)
    maps = r.maps(scene.intrinsics, scene.world_from_camera, small.shape[1], small.shape[0])
    r.close()
    normals, flat = estimate_point_normals(scene.points_m)
    res = static_mask(
        scene.image, small, maps, scene.world_from_camera[:3, 3], scene.points_m, scene.pixels_px, normals, flat, 0.0
    )
    assert res.status == "ok" and res.num_occluding > 100
    assert iou(res.mask, scene.truth) >= 0.85
    # ground rule alone (no points) hides the basement below the terrain
    ground_only = static_mask(
        scene.image,
        small,
        maps,
        scene.world_from_camera[:3, 3],
        np.zeros((0, 3)),
        np.zeros((0, 2)),
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.float32),
        0.0,
    )
    below = cv2.resize((maps.point_in_world_m[..., 2] < -0.3).astype(np.uint8), scene.image.shape[1::-1]) > 0
    assert ground_only.status == "ok"
    assert np.count_nonzero(ground_only.mask[below]) / np.count_nonzero(below) > 0.9


def test_static_without_points_or_terrain_is_not_enough(scene) -> None:
    small = _small(scene.image)
    r = ModelView(scene.model_meshes)
    maps = r.maps(scene.intrinsics, scene.world_from_camera, small.shape[1], small.shape[0])
    r.close()
    res = static_mask(
        scene.image,
        small,
        maps,
        scene.world_from_camera[:3, 3],
        np.zeros((0, 3)),
        np.zeros((0, 2)),
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.float32),
        None,
    )
    assert res.status == "not_enough_views" and not res.mask.any()


def test_terrain_height_from_cloud(scene) -> None:
    normals, flat = estimate_point_normals(scene.points_m)
    z = estimate_terrain_height(scene.points_m, normals, flat)
    assert z is not None and abs(z - 0.0) < 0.1
    assert estimate_terrain_height(scene.points_m[:5], normals[:5], flat[:5]) is None


def test_propagation_spreads_only_to_similar_adjacent_superpixels() -> None:
    # four superpixels in a row: [occluded][unknown, same colour][unknown, other colour][clear]
    labels = np.repeat(np.repeat(np.arange(4, dtype=np.int32)[None, :], 10, axis=0), 10, axis=1)
    lab = np.zeros((10, 40, 3), np.uint8)
    lab[:, :20] = (120, 130, 140)
    lab[:, 20:] = (60, 128, 128)
    state = np.array([1, 0, 0, -1], np.int8)
    out = propagate_labels(labels, lab, state, rounds=3, max_dist=6.0)
    assert out.tolist() == [1, 1, -1, -1]
    assert propagate_labels(labels, lab, state, rounds=0, max_dist=6.0).tolist() == [1, 0, 0, -1]


def test_terrain_height_ignores_floor_slabs_above_the_footprint() -> None:
    rng = np.random.default_rng(3)
    # A big first-floor slab at z = 3.4 m over the 10 x 10 m footprint outweighs a strip of ground at z = 0.
    slab = np.c_[rng.uniform(0, 10, (600, 2)), np.full(600, 3.4)]
    ground = np.c_[rng.uniform(12, 20, (200, 1)), rng.uniform(-5, 15, (200, 1)), np.zeros(200)]
    pts = np.vstack([slab, ground]) + rng.normal(0, 0.005, (800, 3))
    normals, flat = estimate_point_normals(pts)
    assert abs(estimate_terrain_height(pts, normals, flat) - 3.4) < 0.1  # the slab wins without the model
    footprint = (np.array([0.0, 0.0]), np.array([10.0, 10.0]))
    z = estimate_terrain_height(pts, normals, flat, footprint_xy_m=footprint)
    assert z is not None and abs(z) < 0.1


def test_harmonic_propagation_follows_colour_regions() -> None:
    # five superpixels in a row: [occluded][unknown][unknown] in one colour, [unknown][clear] in another
    labels = np.repeat(np.repeat(np.arange(5, dtype=np.int32)[None, :], 10, axis=0), 10, axis=1)
    lab = np.zeros((10, 50, 3), np.uint8)
    lab[:, :30] = (120, 130, 140)
    lab[:, 30:] = (60, 128, 128)
    f = harmonic_labels(labels, lab, np.array([1, 0, 0, 0, -1], np.int8), sigma_lab=2.0)
    assert f[0] == 1.0 and f[4] == 0.0
    assert f[1] > 0.99 and f[2] > 0.99  # the label crosses any number of same-colour superpixels
    assert f[3] < 0.01  # and stops at the colour edge
    # without any label nothing is occluded
    assert not harmonic_labels(labels, lab, np.zeros(5, np.int8), 2.0).any()


@pytest.mark.parametrize(("seed", "num_points", "min_iou"), [(11, 40, 0.85), (11, 100, 0.9), (12, 100, 0.75)])
def test_static_mask_from_few_points(seed: int, num_points: int, min_iou: float) -> None:
    """Few sparse points (a far fixed camera, a phone photo with one partner view): the harmonic spreading of
    the superpixel labels recovers the fence at least as well as the greedy rounds."""
    sc = static_scene(seed, num_points=num_points)
    small = _small(sc.image)
    r = ModelView(sc.model_meshes)
    maps = r.maps(sc.intrinsics, sc.world_from_camera, small.shape[1], small.shape[0])
    r.close()
    normals, flat = estimate_point_normals(sc.points_m)
    centre = sc.world_from_camera[:3, 3]
    args = (sc.image, small, maps, centre, sc.points_m, sc.pixels_px, normals, flat, 0.0)
    harmonic = iou(static_mask(*args).mask, sc.truth)
    rounds = iou(static_mask(*args, StaticParams(propagation="rounds")).mask, sc.truth)
    assert harmonic >= min_iou
    assert harmonic >= rounds - 0.01
