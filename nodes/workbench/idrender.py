"""Element-index and depth images of the model seen by a photo's camera (headless EGL through pyrender).

A minimal server-side renderer for the workbench (selection by region, annotation transfer, peeks): the
triangles of the standing elements are drawn with flat per-vertex colours that encode the element index, into an
undistorted image covering the photo's field of view; the result is resampled (nearest neighbour, ids stay exact)
through the photo's radial distortion onto its pixel grid, scaled to at most ``max_width_px``.

Outputs at the scaled photo size: ``ids`` int32 (h, w), element index + 1 (0 = nothing); ``depth_m`` float32
(h, w), camera z in metres (0 = nothing). The EGL context is thread-bound: create and use an :class:`IdRenderer`
on one thread.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.gl import offscreen_renderer
from nodes.workbench.geometry import ModelGeometry
from schemas.messages import Intrinsics

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

MARGIN_PX = 4
MAX_RENDER_SIDE_PX = 4096


@dataclass(frozen=True)
class IdImage:
    """Renders at ``scale`` x the photo size (see module docstring)."""

    ids: NDArray[np.int32]
    depth_m: NDArray[np.float32]
    scale: float

    def to_photo_px(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Photo pixels of (N, 2) pixels of this render (OpenCV centres)."""
        return (np.asarray(xy, np.float64) + 0.5) / self.scale - 0.5

    def from_photo_px(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixels of this render of (N, 2) photo pixels."""
        return (np.asarray(xy, np.float64) + 0.5) * self.scale - 0.5


def scaled_intrinsics(intr: Intrinsics, scale: float) -> Intrinsics:
    """The same camera for its image resized by ``scale`` (sizes rounded)."""
    return cam.scaled_intrinsics(intr, max(1, round(intr.width_px * scale)), max(1, round(intr.height_px * scale)))


class IdRenderer:
    """ID / depth renders of one :class:`ModelGeometry` (see module docstring)."""

    def __init__(self, geometry: ModelGeometry) -> None:
        import pyrender

        self._pr = pyrender
        self.geometry = geometry
        self._renderer: Any = None
        self._meshes: OrderedDict[bytes, object] = OrderedDict()
        self._maps: OrderedDict[tuple, tuple] = OrderedDict()
        idx = np.repeat(geometry.tri_owner.astype(np.int64) + 1, 3)
        self._colors = np.stack([(idx >> 16) & 255, (idx >> 8) & 255, idx & 255, np.full_like(idx, 255)], 1).astype(
            np.uint8
        )
        self._positions = geometry.tri.reshape(-1, 3).astype(np.float32)

    def _mesh(self, visible: NDArray[np.bool_]) -> object | None:
        key = np.packbits(visible).tobytes()
        if key in self._meshes:
            self._meshes.move_to_end(key)
            return self._meshes[key]
        keep = np.repeat(visible[self.geometry.tri_owner], 3)
        mesh = None
        if keep.any():
            prim = self._pr.Primitive(positions=self._positions[keep], color_0=self._colors[keep], mode=4)
            mesh = self._pr.Mesh([prim])
        self._meshes[key] = mesh
        while len(self._meshes) > 8:
            self._meshes.popitem(last=False)
        return mesh

    def _undistort_maps(self, intr: Intrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32], Intrinsics]:
        """Per-pixel sampling maps into an undistorted render, and that render's pinhole intrinsics."""
        key = (intr.width_px, intr.height_px, intr.f_px, intr.cx_px, intr.cy_px, intr.k1, intr.k2, intr.fy_over_fx)
        if key in self._maps:
            return self._maps[key]
        w, h = intr.width_px, intr.height_px
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = cam.pixels_to_normalized(intr, np.c_[uu.ravel(), vv.ravel()])
        fx, fy = cam.focal_xy(intr)
        lo, hi = xy.min(0), xy.max(0)
        cx = -fx * lo[0] + MARGIN_PX
        cy = -fy * lo[1] + MARGIN_PX
        rw = min(MAX_RENDER_SIDE_PX, int(np.ceil(fx * (hi[0] - lo[0]))) + 2 * MARGIN_PX + 1)
        rh = min(MAX_RENDER_SIDE_PX, int(np.ceil(fy * (hi[1] - lo[1]))) + 2 * MARGIN_PX + 1)
        mx = (fx * xy[:, 0] + cx).reshape(h, w).astype(np.float32)
        my = (fy * xy[:, 1] + cy).reshape(h, w).astype(np.float32)
        pin = Intrinsics(width_px=rw, height_px=rh, f_px=fx, cx_px=cx, cy_px=cy, fy_over_fx=intr.fy_over_fx)
        self._maps[key] = (mx, my, pin)
        while len(self._maps) > 16:
            self._maps.popitem(last=False)
        return mx, my, pin

    def render(self, camera: cam.PinholeCamera, visible: NDArray[np.bool_], max_width_px: int = 960) -> IdImage:
        """IDs and depth of the ``visible`` (E,) elements seen by ``camera``, at most ``max_width_px`` wide."""
        pr = self._pr
        intr = camera.intrinsics
        scale = min(1.0, max_width_px / intr.width_px)
        intr_s = scaled_intrinsics(intr, scale) if scale < 1.0 else intr
        mx, my, pin = self._undistort_maps(intr_s)
        mesh = self._mesh(visible)
        h, w = intr_s.height_px, intr_s.width_px
        if mesh is None:
            return IdImage(np.zeros((h, w), np.int32), np.zeros((h, w), np.float32), scale)
        near = 0.05
        centre = camera.center_in_world_m
        far = float(np.linalg.norm(self.geometry.bbox_max_m - self.geometry.bbox_min_m)) + float(
            np.linalg.norm(centre - (self.geometry.bbox_max_m + self.geometry.bbox_min_m) / 2)
        )
        fx, fy = cam.focal_xy(pin)
        # pyrender's IntrinsicsCamera takes the principal point in pixel-edge coordinates (+0.5 from OpenCV's).
        pcam = pr.IntrinsicsCamera(fx, fy, pin.cx_px + 0.5, pin.cy_px + 0.5, znear=near, zfar=max(far * 1.5, 1.0))
        scene = pr.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
        scene.add(mesh)
        gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
        scene.add(pcam, pose=camera.world_from_camera @ gl_from_cv)
        if self._renderer is None:
            self._renderer = offscreen_renderer(pin.width_px, pin.height_px)
        r = self._renderer
        r.viewport_width, r.viewport_height = pin.width_px, pin.height_px
        color, depth = r.render(scene, flags=pr.RenderFlags.FLAT | pr.RenderFlags.SKIP_CULL_FACES)
        ids_u = (color[..., 0].astype(np.int32) << 16) | (color[..., 1].astype(np.int32) << 8) | color[..., 2]
        ids = cv2.remap(ids_u.astype(np.float32), mx, my, cv2.INTER_NEAREST, borderValue=0).astype(np.int32)
        dep = cv2.remap(depth.astype(np.float32), mx, my, cv2.INTER_NEAREST, borderValue=0)
        return IdImage(ids=ids, depth_m=np.asarray(dep, np.float32), scale=scale)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None
