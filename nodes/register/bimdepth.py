"""BIM depth at pixels: the model's surface seen from a camera at a date (anchor features get 3D points from it)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from constructaide import camera as cam
from constructaide.modelview import ModelView
from schemas.messages import GeoPoint, Intrinsics

DepthLookup = Callable[[np.ndarray, Intrinsics, np.ndarray, int], np.ndarray]
"""``depth_lookup(world_from_camera (4, 4), intrinsics, pixels_px (N, 2), capture_time_ns) -> depth_m (N,)``:
camera z of the model surface each pixel sees at that time (NaN where nothing is hit)."""


class MeshDepthLookup:
    """Depth of the BIM at pixels (:data:`DepthLookup`), on the shared model view (:class:`ModelView`, headless
    EGL): ``meshes`` ``{name: (vertices (N, 3), faces (M, 3))}``, ``elements_at(t_ns)`` names the meshes standing at
    a time (None: all), ``ground_height_m`` adds the terrain as a horizontal plane (z up: buried footings hidden,
    ground features get their depth). Pixels on depth discontinuities (3x3 spread above ``max_relative_spread``)
    get NaN. Use from one thread (the node's worker)."""

    def __init__(
        self,
        meshes: dict[str, tuple[np.ndarray, np.ndarray]],
        elements_at: Callable[[int], set[str] | None] | None = None,
        max_relative_spread: float = 0.03,
        ground_height_m: float | None = None,
        site_gps: GeoPoint | None = None,
        origin_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        self.view = ModelView({n: (v, f) for n, (v, f) in meshes.items() if len(v) and len(f)})
        if self.view.empty:
            raise ValueError("the BIM model has no triangles to look depth up in")
        self.elements_at = elements_at
        self.max_relative_spread = max_relative_spread
        self.ground_height_m = ground_height_m
        self.site_gps = site_gps
        """The site reference's geographic position (IfcSite; map x east, y north), when known."""
        self.origin_offset_m = origin_offset_m
        """Subtracted from map coordinates to give the model's (the ingest's automatic offset)."""

    def elements(self, capture_time_ns: int) -> set[str] | None:
        """Mesh names standing at a time (None: all)."""
        return self._elements(capture_time_ns)

    def _elements(self, capture_time_ns: int) -> set[str] | None:
        return self.elements_at(capture_time_ns) if self.elements_at is not None else None

    def depth_map(self, world_from_camera: np.ndarray, intr: Intrinsics, capture_time_ns: int = 0) -> np.ndarray:
        """(H, W) float32 camera-z depth (m) of an undistorted pinhole render at that date (0 where nothing)."""
        return self.view.depth_map(world_from_camera, intr, self._elements(capture_time_ns), self.ground_height_m)

    def __call__(
        self, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray, capture_time_ns: int = 0
    ) -> np.ndarray:
        return self.view.depth_at(
            world_from_camera,
            intr,
            np.asarray(pixels_px, np.float64),
            self._elements(capture_time_ns),
            self.ground_height_m,
            self.max_relative_spread,
        )

    def close(self) -> None:
        self.view.close()


def points_from_depth(
    lookup: DepthLookup, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray, capture_time_ns: int
) -> np.ndarray:
    """World points (N, 3) m of the model surface seen at pixels (N, 2) through a camera (NaN rows where nothing
    is hit), from a depth lookup."""
    px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
    pts = np.full((len(px), 3), np.nan)
    if len(px) == 0:
        return pts
    depth = np.asarray(lookup(world_from_camera, intr, px, capture_time_ns), np.float64).reshape(-1)
    ok = np.isfinite(depth) & (depth > 0)
    xy = cam.pixels_to_normalized(intr, px[ok])
    p_cam = np.c_[xy, np.ones(len(xy))] * depth[ok, None]
    pts[ok] = p_cam @ np.asarray(world_from_camera)[:3, :3].T + np.asarray(world_from_camera)[:3, 3]
    return pts
