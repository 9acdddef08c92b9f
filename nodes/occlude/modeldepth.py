"""Depth, normals and world points of the BIM seen from a registered camera (pyrender, EGL).

The model is rendered as a pinhole image at the working resolution (with a margin when the lens
has radial distortion), then remapped onto the distorted pixel grid of the photo. Normals come
from the depth map (cross product of one-sided differences, the side with the smaller depth jump,
so that depth edges do not smear); they are exact on planar faces, which is what building elements
are made of.

The OpenGL context belongs to the thread that first calls :meth:`ModelRenderer.render`; call it
from one thread only (the node's worker thread).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

import constructaide  # noqa: F401  (sets PYOPENGL_PLATFORM=egl before pyrender is imported)
from constructaide.camera import focal_xy, pixels_to_normalized
from constructaide.gl import offscreen_renderer
from schemas.messages import Intrinsics

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Mesh = tuple[NDArray[np.float64], NDArray[np.int32]]

_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class ModelMaps:
    """Per-pixel model geometry for one camera at one image size (h, w).

    ``depth_m``: float32 camera z in metres, ``inf`` where no model; ``normal_in_world``: float32
    (h, w, 3) unit normals (zero where no model), oriented towards the camera;
    ``point_in_world_m``: float32 (h, w, 3) surface points (NaN where no model).
    """

    depth_m: F32
    normal_in_world: F32
    point_in_world_m: F32

    @property
    def has_model(self) -> NDArray[np.bool_]:
        return np.isfinite(self.depth_m)


def scaled_intrinsics(intr: Intrinsics, width_px: int, height_px: int) -> Intrinsics:
    """Intrinsics of the same camera for an image resized to (width_px, height_px): fx scales with the width, fy
    with the height (so a resize that changes the aspect changes ``fy_over_fx``)."""
    if intr.width_px <= 0 or intr.height_px <= 0 or intr.f_px <= 0:
        raise ValueError(f"intrinsics need a positive image size and focal length, got {intr}")
    sx = width_px / intr.width_px
    sy = height_px / intr.height_px
    return Intrinsics(
        width_px=width_px,
        height_px=height_px,
        f_px=intr.f_px * sx,
        cx_px=sx * (intr.cx_px + 0.5) - 0.5,
        cy_px=sy * (intr.cy_px + 0.5) - 0.5,
        k1=intr.k1,
        k2=intr.k2,
        fy_over_fx=intr.fy_over_fx * sy / sx,
    )


def normals_from_depth(depth_m: F32, intr: Intrinsics) -> tuple[F32, F32]:
    """Camera-frame points (h, w, 3) and unit normals (h, w, 3) of a pinhole depth map.

    Normals face the camera; pixels without depth get NaN points and zero normals.
    """
    h, w = depth_m.shape
    fx, fy = focal_xy(intr)
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    z = depth_m.astype(np.float32)
    x = (u - intr.cx_px) / fx * z
    y = (v - intr.cy_px) / fy * z
    pts = np.stack([x, y, z], axis=-1)
    pts[~np.isfinite(z)] = np.nan

    def one_sided(axis: int) -> F32:
        fwd = np.roll(pts, -1, axis=axis) - pts
        bwd = pts - np.roll(pts, 1, axis=axis)
        fz = np.abs(fwd[..., 2])
        bz = np.abs(bwd[..., 2])
        fz = np.where(np.isfinite(fz), fz, np.inf)
        bz = np.where(np.isfinite(bz), bz, np.inf)
        return np.where((fz <= bz)[..., None], fwd, bwd)

    du = one_sided(1)
    dv = one_sided(0)
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    # orient towards the camera (camera at origin): n . p < 0
    flip = np.sum(n * pts, axis=-1) > 0
    n[flip] *= -1.0
    n[~np.isfinite(n).all(axis=-1)] = 0.0
    return pts.astype(np.float32), n.astype(np.float32)


class ModelRenderer:
    """Renders depth of a fixed set of meshes (site-local metres, z up) for arbitrary cameras."""

    def __init__(self, meshes: Mapping[str, Mesh], z_near_m: float = 0.05, z_far_m: float = 5000.0) -> None:
        verts: list[NDArray[np.float64]] = []
        faces: list[NDArray[np.int64]] = []
        offset = 0
        for v, f in meshes.values():
            v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
            f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
            if len(v) == 0 or len(f) == 0:
                continue
            verts.append(v)
            faces.append(f + offset)
            offset += len(v)
        self.vertices_m = np.concatenate(verts) if verts else np.zeros((0, 3))
        self.faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        self.z_near_m = z_near_m
        self.z_far_m = z_far_m
        self._thread: int | None = None
        self._renderer = None
        self._scene = None
        self._cam_node = None

    @property
    def empty(self) -> bool:
        return len(self.faces) == 0

    def _ensure_scene(self) -> None:
        import pyrender
        import trimesh

        if self._thread is not None and self._thread != threading.get_ident():
            raise RuntimeError("ModelRenderer.render must be called from the thread that created its GL context")
        if self._scene is None:
            self._thread = threading.get_ident()
            self._scene = pyrender.Scene(bg_color=(0, 0, 0, 0))
            mesh = trimesh.Trimesh(self.vertices_m, self.faces, process=False)
            self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))

    def _render_pinhole(self, intr: Intrinsics) -> F32:
        """Depth (h, w) float32 metres (inf = no model) of an undistorted pinhole camera."""
        import pyrender

        self._ensure_scene()
        assert self._scene is not None
        w, h = intr.width_px, intr.height_px
        if self._renderer is None:
            self._renderer = offscreen_renderer(w, h)
        else:
            self._renderer.viewport_width, self._renderer.viewport_height = w, h
        # pyrender's cx is measured from the left edge of the image; ours from the first pixel centre.
        fx, fy = focal_xy(intr)
        cam = pyrender.IntrinsicsCamera(
            fx, fy, intr.cx_px + 0.5, intr.cy_px + 0.5, znear=self.z_near_m, zfar=self.z_far_m
        )
        if self._cam_node is not None:
            self._scene.remove_node(self._cam_node)
        self._cam_node = self._scene.add(cam, pose=self._pose)
        depth = self._renderer.render(self._scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
        depth = np.asarray(depth, dtype=np.float32)
        depth[depth <= 0] = np.inf
        return depth

    def render(self, intr: Intrinsics, world_from_camera: F64, width_px: int, height_px: int) -> ModelMaps:
        """Model maps for a camera (full-resolution ``intr``) at image size (width_px, height_px)."""
        target = scaled_intrinsics(intr, width_px, height_px)
        world_from_camera = np.asarray(world_from_camera, dtype=np.float64).reshape(4, 4)
        if self.empty:
            return ModelMaps(
                np.full((height_px, width_px), np.inf, np.float32),
                np.zeros((height_px, width_px, 3), np.float32),
                np.full((height_px, width_px, 3), np.nan, np.float32),
            )
        self._pose = world_from_camera @ _OPENGL_FROM_OPENCV
        distorted = target.k1 != 0.0 or target.k2 != 0.0
        if distorted:
            # undistorted normalised coordinates of every target pixel, and a pinhole canvas covering them
            uu, vv = np.meshgrid(np.arange(width_px, dtype=np.float64), np.arange(height_px, dtype=np.float64))
            xy = pixels_to_normalized(target, np.stack([uu.ravel(), vv.ravel()], axis=1))
            # strong distortion can fold the undistortion outwards: keep the canvas within three times the
            # pinhole field of view (pixels beyond it show no model)
            fxy = np.array(focal_xy(target))
            half = np.array([width_px, height_px], np.float64) / fxy
            centre = np.array([target.cx_px, target.cy_px]) / fxy
            lo, hi = -centre - half, -centre + 2.0 * half
            xy = np.where(np.isfinite(xy), xy, 1e9)
            x_min, y_min = np.maximum(xy.min(axis=0), lo)
            x_max, y_max = np.minimum(xy.max(axis=0), hi)
            fx, fy = fxy
            pad = 2.0
            cx = -x_min * fx + pad
            cy = -y_min * fy + pad
            cw = int(np.ceil((x_max - x_min) * fx + 2 * pad)) + 1
            ch = int(np.ceil((y_max - y_min) * fy + 2 * pad)) + 1
            pin = Intrinsics(width_px=cw, height_px=ch, f_px=fx, cx_px=cx, cy_px=cy, fy_over_fx=target.fy_over_fx)
        else:
            pin = Intrinsics(
                width_px=width_px,
                height_px=height_px,
                f_px=target.f_px,
                cx_px=target.cx_px,
                cy_px=target.cy_px,
                fy_over_fx=target.fy_over_fx,
            )
        depth_pin = self._render_pinhole(pin)
        pts_cam, n_cam = normals_from_depth(depth_pin, pin)
        if distorted:
            pfx, pfy = focal_xy(pin)
            map_x = (xy[:, 0] * pfx + pin.cx_px).reshape(height_px, width_px).astype(np.float32)
            map_y = (xy[:, 1] * pfy + pin.cy_px).reshape(height_px, width_px).astype(np.float32)
            stacked = np.concatenate([pts_cam, n_cam], axis=-1)
            remapped = cv2.remap(
                stacked, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
            )
            pts_cam, n_cam = remapped[..., :3], remapped[..., 3:]
            n_cam = np.nan_to_num(n_cam, nan=0.0)
        depth = pts_cam[..., 2].copy()
        depth[~np.isfinite(depth)] = np.inf
        R = world_from_camera[:3, :3].astype(np.float32)
        t = world_from_camera[:3, 3].astype(np.float32)
        pts_world = pts_cam @ R.T + t
        n_world = n_cam @ R.T
        return ModelMaps(depth.astype(np.float32), n_world.astype(np.float32), pts_world.astype(np.float32))

    def close(self) -> None:
        """Free the GL context (only from its own thread; elsewhere the references are dropped)."""
        if self._renderer is not None and self._thread == threading.get_ident():
            self._renderer.delete()
        self._renderer = None
        self._scene = None
        self._cam_node = None
        self._thread = None
