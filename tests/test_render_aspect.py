"""Rasters of a camera with non-square pixels (fy / fx = 1.02): the element-ID and depth rasters of the render node
and the occlusion node's model depth follow the projection with fy = 1.02 fx, not a square-pixel one."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import four_box_model

import constructaide  # noqa: F401  (EGL platform)
from constructaide.camera import centered_intrinsics, invert_rigid, look_at, project_points, scaled_intrinsics
from constructaide.modelscene import scene_from_model
from constructaide.modelview import GLRasterizer, ModelView

ASPECT = 1.02
W, H = 1280, 800
WFC = look_at((4.5, -10.0, 3.0), (4.5, 0.0, 1.0))


def _camera(k1: float, aspect: float = ASPECT):
    return centered_intrinsics(W, H, 0.75 * W, k1=k1, k2=0.01 if k1 else 0.0, fy_over_fx=aspect)


def _edge_rows(intr, x: float) -> tuple[float, float]:
    """Rows (float px) of box A's front face top (z = 3) and bottom (z = 0) edges at x."""
    uv, _ = project_points(intr, invert_rigid(WFC), [(x, -1.0, 3.0), (x, -1.0, 0.0)])
    return float(uv[0, 1]), float(uv[1, 1])


@pytest.fixture(scope="module")
def ras():
    r = GLRasterizer()
    yield r
    r.close()


@pytest.mark.parametrize("k1", [0.0, -0.08])
def test_id_and_depth_rasters_follow_the_pixel_aspect(ras, k1: float) -> None:
    model = four_box_model()
    scene = scene_from_model(model)
    intr = _camera(k1)
    res = ras.render(scene, intr, WFC, np.ones(scene.num_elements + 1, bool))
    a = scene.index_of["A"]
    rng = np.random.default_rng(0)
    # Points on box A's front face (y = -1), away from its edges: ID and depth where they project.
    pts = np.c_[rng.uniform(-0.85, 0.85, 200), np.full(200, -1.0), rng.uniform(0.1, 2.9, 200)]
    uv, z = project_points(intr, invert_rigid(WFC), pts)
    r, c = np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)
    assert np.mean(res.ids[r, c] == a) > 0.99
    assert np.allclose(res.depth_m[r, c], z, atol=0.02)
    # The face's top and bottom edges in the raster, down one column, are where the aspect puts them (within a
    # pixel); its height there is the aspect's, 2 % (~6 px) more than square pixels give.
    col = int(round(project_points(intr, invert_rigid(WFC), [(0.0, -1.0, 1.5)])[0][0, 0]))
    rows = np.flatnonzero(res.ids[:, col] == a)
    top, bottom = _edge_rows(intr, 0.0)
    assert abs(rows.min() - top) <= 1.0 and abs(rows.max() - bottom) <= 1.0
    sq_top, sq_bottom = _edge_rows(_camera(k1, 1.0), 0.0)
    height = rows.max() - rows.min()
    assert abs(height - (bottom - top)) <= 1.5 and abs(height - (sq_bottom - sq_top)) > 4.0


@pytest.mark.parametrize("k1", [0.0, -0.08])
def test_model_depth_follows_the_pixel_aspect(k1: float) -> None:
    from render_scenes import box

    heights = {}
    for aspect in (ASPECT, 1.0):
        intr = _camera(k1, aspect)
        r = ModelView({"A": box((0.0, 0.0, 1.5), (2, 2, 3))})
        maps = r.maps(intr, WFC, W // 2, H // 2)
        r.close()
        small = scaled_intrinsics(intr, W // 2, H // 2)
        assert small.fy_over_fx == pytest.approx(aspect)
        rng = np.random.default_rng(1)
        pts = np.c_[rng.uniform(-0.85, 0.85, 200), np.full(200, -1.0), rng.uniform(0.1, 2.9, 200)]
        uv, z = project_points(small, invert_rigid(WFC), pts)
        rr, cc = np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)
        assert np.allclose(maps.depth_m[rr, cc], z, rtol=0.01)
        assert np.allclose(maps.point_in_world_m[rr, cc], pts, atol=0.05)
        col = int(round(project_points(small, invert_rigid(WFC), [(0.0, -1.0, 1.5)])[0][0, 0]))
        rows = np.flatnonzero(np.isfinite(maps.depth_m[:, col]))
        top, bottom = _edge_rows(small, 0.0)
        # The distorted path resamples a pinhole canvas by nearest neighbour: its bottom edge comes ~1.4 px short
        # with square pixels too.
        tol = 1.0 if k1 == 0.0 else 2.0
        assert abs(rows.min() - top) <= tol and abs(rows.max() - bottom) <= tol
        heights[aspect] = (rows.max() - rows.min(), bottom - top)
    # The aspect stretches the face by 2 % (~3 px at this size) against square pixels, as the projection does.
    rendered = heights[ASPECT][0] - heights[1.0][0]
    projected = heights[ASPECT][1] - heights[1.0][1]
    assert projected > 2.5 and abs(rendered - projected) <= 1.0


def test_resized_intrinsics_keep_the_aspect() -> None:
    intr = _camera(-0.08)
    for scaled in (scaled_intrinsics(intr, 640, 400), scaled_intrinsics(intr, 640, 400)):
        assert scaled.f_px == pytest.approx(intr.f_px / 2) and scaled.fy_over_fx == pytest.approx(ASPECT)
    # A resize that changes the image's aspect changes the pixels' (fy scales with the height).
    squashed = scaled_intrinsics(intr, 640, 200)
    assert squashed.f_px * squashed.fy_over_fx == pytest.approx(intr.f_px * ASPECT / 4)
