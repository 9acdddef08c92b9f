"""Pixel regions of photos: outlines of elements from ID renders, lasso / polygon / brush masks, the elements a
region covers, regions carried through the model surface to another photo, and homography peeks (pure: numpy, cv2).

All arrays are at one render's pixel grid (OpenCV convention); ``ids`` is element index + 1 (0 = nothing), as
:class:`nodes.workbench.idrender.IdImage`; polygons are lists of (x, y) pixels of that grid.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam

Polygon = list[tuple[float, float]]
MIN_COVER_FRACTION = 0.5  # an element is in a region when this share of its visible pixels is inside
DEPTH_TOLERANCE = 0.03  # a lifted point is visible in another photo when within 3 % (>= 5 cm) of its depth


def mask_polygons(mask: NDArray[np.bool_], min_area_px: float = 4.0, tolerance_px: float = 0.7) -> list[Polygon]:
    """Outer outlines (and holes, as separate rings) of a binary mask, simplified by ``tolerance_px``."""
    m = np.ascontiguousarray(mask, np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    out: list[Polygon] = []
    for c in contours:
        if cv2.contourArea(c) < min_area_px and len(c) < 8:
            continue
        c = cv2.approxPolyDP(c, tolerance_px, True)
        if len(c) >= 3:
            out.append([(float(x), float(y)) for x, y in c.reshape(-1, 2)])
    return out


def element_mask(ids: NDArray[np.int32], element_indices: Sequence[int]) -> NDArray[np.bool_]:
    """Pixels showing any of the 0-based ``element_indices``."""
    if len(element_indices) == 0:
        return np.zeros(ids.shape, bool)
    lut = np.zeros(int(max(ids.max(), max(element_indices) + 1)) + 1, bool)
    lut[np.asarray(element_indices, np.int64) + 1] = True
    return lut[ids]


def region_mask(
    shape: tuple[int, int],
    polygon: Sequence[tuple[float, float]] | None = None,
    brush: Sequence[tuple[float, float]] | None = None,
    radius_px: float = 10.0,
) -> NDArray[np.bool_]:
    """(h, w) bool of a closed polygon (lasso or clicked vertices) or a brush stroke of ``radius_px``."""
    m = np.zeros(shape, np.uint8)
    if polygon is not None and len(polygon) >= 3:
        cv2.fillPoly(m, [np.round(np.asarray(polygon, np.float64)).astype(np.int32)], 1)
    if brush is not None and len(brush) >= 1:
        pts = np.round(np.asarray(brush, np.float64)).astype(np.int32)
        r = max(1, round(radius_px))
        for p in pts:
            cv2.circle(m, (int(p[0]), int(p[1])), r, 1, -1)
        if len(pts) > 1:
            cv2.polylines(m, [pts], False, 1, thickness=2 * r)
    return m.astype(bool)


def elements_in_region(
    ids: NDArray[np.int32], region: NDArray[np.bool_], min_fraction: float = MIN_COVER_FRACTION
) -> list[int]:
    """0-based indices of elements with at least ``min_fraction`` of their visible pixels inside ``region``, most
    covered first."""
    total = np.bincount(ids.ravel())
    inside = np.bincount(ids[region].ravel(), minlength=len(total))
    frac = np.divide(inside, total, out=np.zeros(len(total)), where=total > 0)
    frac[0] = 0.0
    chosen = np.nonzero(frac >= min_fraction)[0]
    return [int(i) - 1 for i in chosen[np.argsort(-inside[chosen], kind="stable")]]


def component_at(mask: NDArray[np.bool_], x: float, y: float) -> NDArray[np.bool_]:
    """The connected part of ``mask`` under pixel (x, y) (empty when the pixel is outside the mask)."""
    xi, yi = round(x), round(y)
    h, w = mask.shape
    if not (0 <= xi < w and 0 <= yi < h) or not mask[yi, xi]:
        return np.zeros(mask.shape, bool)
    _, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    return labels == labels[yi, xi]


def lift_region(
    region: NDArray[np.bool_], depth_m: NDArray[np.float32], camera: cam.PinholeCamera, step_px: int = 2
) -> NDArray[np.float64]:
    """(N, 3) world points of the model surface under ``region`` (every ``step_px`` pixel with depth), for
    ``camera`` at this grid's scale."""
    sub = np.zeros_like(region)
    sub[::step_px, ::step_px] = True
    vv, uu = np.nonzero(region & sub & (depth_m > 0))
    if len(uu) == 0:
        return np.zeros((0, 3))
    xy = cam.pixels_to_normalized(camera.intrinsics, np.c_[uu, vv])
    p_cam = np.c_[xy, np.ones(len(xy))] * depth_m[vv, uu][:, None]
    return p_cam @ camera.world_from_camera[:3, :3].T + camera.world_from_camera[:3, 3]


def project_region(
    points_in_world_m: NDArray[np.float64],
    camera: cam.PinholeCamera,
    depth_m: NDArray[np.float32],
    splat_px: int = 2,
) -> NDArray[np.bool_]:
    """(h, w) bool: pixels of ``camera`` (at ``depth_m``'s grid) where the surface points are visible (their depth
    matches the render's within :data:`DEPTH_TOLERANCE`), splatted and closed to a region."""
    h, w = depth_m.shape
    out = np.zeros((h, w), np.uint8)
    if len(points_in_world_m) == 0:
        return out.astype(bool)
    px, z = camera.project(points_in_world_m)
    ui, vi = np.round(px[:, 0]), np.round(px[:, 1])
    ok = (z > 0) & np.isfinite(ui) & np.isfinite(vi) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ui, vi, z = ui[ok].astype(np.int64), vi[ok].astype(np.int64), z[ok]
    d = depth_m[vi, ui]
    seen = (d > 0) & (np.abs(d - z) <= np.maximum(DEPTH_TOLERANCE * z, 0.05))
    out[vi[seen], ui[seen]] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * splat_px + 1, 2 * splat_px + 1))
    closed = cv2.morphologyEx(cv2.dilate(out, k), cv2.MORPH_CLOSE, k)
    return (closed > 0) & (depth_m > 0)


def warp_region(
    neighbour_rgb: NDArray[np.uint8],
    this_from_neighbour: NDArray[np.float64],
    out_shape: tuple[int, int],
    region: NDArray[np.bool_] | None,
) -> NDArray[np.uint8]:
    """RGBA (h, w, 4): the neighbour photo warped into this photo's pixels by the (3, 3) homography, opaque inside
    ``region`` (everywhere when None) where the warp has pixels."""
    h, w = out_shape
    warped = cv2.warpPerspective(neighbour_rgb, this_from_neighbour, (w, h), flags=cv2.INTER_LINEAR)
    cover = cv2.warpPerspective(np.full(neighbour_rgb.shape[:2], 255, np.uint8), this_from_neighbour, (w, h))
    alpha = np.where(cover > 127, 255, 0).astype(np.uint8)
    if region is not None:
        alpha[~region] = 0
    return np.dstack([warped, alpha])


def scale_homography(H: NDArray[np.float64], scale: float) -> NDArray[np.float64]:
    """The homography between two photos both resized by ``scale`` (pixel centres kept)."""
    S = np.array([[scale, 0, 0.5 * scale - 0.5], [0, scale, 0.5 * scale - 0.5], [0, 0, 1.0]])
    return S @ H @ np.linalg.inv(S)
