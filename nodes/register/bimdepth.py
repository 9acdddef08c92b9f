"""BIM depth at pixels: the model's surface seen from a camera at a date (anchor features get 3D points from it)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from constructaide import camera as cam
from constructaide.gl import offscreen_renderer
from schemas.messages import Intrinsics

DepthLookup = Callable[[np.ndarray, Intrinsics, np.ndarray, int], np.ndarray]
"""``depth_lookup(world_from_camera (4, 4), intrinsics, pixels_px (N, 2), capture_time_ns) -> depth_m (N,)``:
camera z of the model surface each pixel sees at that time (NaN where nothing is hit)."""


def standing_elements(tasks, element_ids) -> Callable[[int], set[str] | None]:
    """``elements_at(t_ns)`` for :class:`MeshDepthLookup`: elements standing at a time by the schedule.

    Actual dates win over planned ones; complete, under-demolition and unscheduled elements stand. Elements
    under construction are left out (their full geometry would hide what is really visible behind them).
    With no tasks every element stands (returns None).
    """
    from constructaide import schedule4d

    windows = schedule4d.element_windows(tasks)
    ids = list(element_ids)
    if not windows:
        return lambda t_ns: None

    def elements_at(t_ns: int) -> set[str]:
        out = set()
        for gid in ids:
            w = windows.get(gid)
            state = schedule4d.actual_state(w, t_ns) or schedule4d.planned_state(w, t_ns)
            if state in ("complete", "under_demolition", "unscheduled"):
                out.add(gid)
        return out

    return elements_at


class MeshDepthLookup:
    """Depth of a triangle mesh (world metres) at pixels: an OpenGL depth render (pyrender, headless EGL).

    Implements :data:`DepthLookup`. ``meshes``: ``{name: (vertices (N, 3), faces (M, 3))}``; ``elements_at(t_ns)``
    names the meshes standing at a time (None: all); ``ground_height_m`` adds the terrain as a horizontal plane
    (z up), which hides buried footings and gives ground features their depth. Pixels are
    undistorted before the lookup; pixels on depth discontinuities (3x3 neighbourhood spread above
    ``max_relative_spread`` of the depth) get NaN, so silhouette features do not take the background's depth.
    The renderer is created lazily and must be used from one thread (the node's worker thread).
    """

    def __init__(
        self,
        meshes: dict[str, tuple[np.ndarray, np.ndarray]],
        elements_at: Callable[[int], set[str] | None] | None = None,
        max_relative_spread: float = 0.03,
        ground_height_m: float | None = None,
        ground_extent_m: float = 300.0,
    ) -> None:
        self.meshes = {
            name: (np.asarray(v, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3))
            for name, (v, f) in meshes.items()
            if len(v) and len(f)
        }
        if not self.meshes:
            raise ValueError("the BIM model has no triangles to look depth up in")
        self.elements_at = elements_at
        self.max_relative_spread = max_relative_spread
        self.ground: tuple[np.ndarray, np.ndarray] | None = None
        if ground_height_m is not None:
            all_v = np.vstack([v for v, _ in self.meshes.values()])
            cx, cy = (all_v[:, 0].min() + all_v[:, 0].max()) / 2, (all_v[:, 1].min() + all_v[:, 1].max()) / 2
            e = ground_extent_m
            gv = np.array([[cx - e, cy - e], [cx + e, cy - e], [cx + e, cy + e], [cx - e, cy + e]])
            self.ground = (np.c_[gv, np.full(4, ground_height_m)], np.array([[0, 1, 2], [0, 2, 3]]))
        self._scene: Any = None
        self._scene_key: frozenset[str] | None = None
        self._renderer: Any = None
        self._size = (0, 0)

    def _scene_for(self, names: frozenset[str]):
        import pyrender
        import trimesh

        if self._scene is None or self._scene_key != names:
            verts, faces, off = [], [], 0
            parts = [self.meshes[n] for n in sorted(names)] + ([self.ground] if self.ground is not None else [])
            for v, f in parts:
                verts.append(v)
                faces.append(f + off)
                off += len(v)
            self._scene = pyrender.Scene()
            if verts:
                mesh = trimesh.Trimesh(vertices=np.vstack(verts), faces=np.vstack(faces), process=False)
                self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
            self._scene_key = names
        return self._scene

    def depth_map(self, world_from_camera: np.ndarray, intr: Intrinsics, capture_time_ns: int = 0) -> np.ndarray:
        """(H, W) float32 camera-z depth in metres of an undistorted pinhole render (0 where nothing is hit).

        Only the elements standing at ``capture_time_ns`` (``elements_at``; all when it is None) are drawn.
        """
        import pyrender

        present = self.elements_at(capture_time_ns) if self.elements_at is not None else None
        names = frozenset(self.meshes) if present is None else frozenset(n for n in self.meshes if n in present)
        if not names:
            return np.zeros((intr.height_px, intr.width_px), np.float32)
        scene = self._scene_for(names)
        size = (intr.width_px, intr.height_px)
        if self._renderer is None or self._size != size:
            if self._renderer is not None:
                self._renderer.delete()
            self._renderer = offscreen_renderer(*size)
            self._size = size
        parts = [self.meshes[n][0] for n in names] + ([self.ground[0]] if self.ground is not None else [])
        far = max(float(np.max(np.linalg.norm(v - world_from_camera[:3, 3], axis=1))) for v in parts) * 1.1 + 1.0
        camera = pyrender.IntrinsicsCamera(
            fx=intr.f_px, fy=cam.focal_xy(intr)[1], cx=intr.cx_px + 0.5, cy=intr.cy_px + 0.5, znear=0.05, zfar=far
        )
        gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
        node = scene.add(camera, pose=np.asarray(world_from_camera, np.float64) @ gl_from_cv)
        try:
            depth = self._renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
        finally:
            scene.remove_node(node)
        return np.asarray(depth, np.float32)

    def __call__(
        self, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray, capture_time_ns: int = 0
    ) -> np.ndarray:
        px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
        out = np.full(len(px), np.nan)
        if len(px) == 0:
            return out
        pinhole = Intrinsics(
            width_px=intr.width_px,
            height_px=intr.height_px,
            f_px=intr.f_px,
            cx_px=intr.cx_px,
            cy_px=intr.cy_px,
            fy_over_fx=intr.fy_over_fx,
        )
        depth = self.depth_map(world_from_camera, pinhole, capture_time_ns)
        lo = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32), np.ones((3, 3), np.uint8))
        hi = cv2.dilate(depth, np.ones((3, 3), np.uint8))
        undist = cam.normalized_to_pixels(pinhole, cam.pixels_to_normalized(intr, px))
        uv = np.round(undist).astype(int)
        h, w = depth.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        u, v = uv[inside, 0], uv[inside, 1]
        d, d_lo, d_hi = depth[v, u], lo[v, u], hi[v, u]
        ok = (d > 0) & np.isfinite(d_lo) & (d_hi - d_lo <= self.max_relative_spread * d)
        vals = np.where(ok, d, np.nan)
        out[np.nonzero(inside)[0]] = vals
        return out

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None


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
