"""The model seen from a camera: element-ID, depth and shade rasters, surface maps and depth lookups.

:class:`GLRasterizer` renders a :class:`constructaide.modelscene.BimScene`; :class:`ModelView` wraps one for a set
of meshes (per-element visibility, optional ground plane) and is what the render, occlude and register nodes use.

The scene is drawn with a small OpenGL 3.3 program (one draw call, no multisampling, integer
colour target) into an *undistorted* image that covers the distorted photo's field of view with
a margin; the result is then resampled (nearest neighbour, so ids stay exact) through the shared
radial distortion model of :mod:`constructaide.camera` onto the photo's pixel grid.

The OpenGL context is EGL (headless) and thread-bound: create and use a :class:`GLRasterizer`
on one thread. Outputs, all (H, W) at photo size, OpenCV pixel convention:

* ``ids`` uint32: 1-based element index, 0 background, :data:`constructaide.modelscene.GROUND_INDEX` ground plane;
* ``depth_m`` float32: camera-frame z in metres, 0 where nothing was hit;
* ``shade`` float32 in [0, 1]: per-face Lambert shade (fixed world light), 0 on background.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide.camera import focal_xy, invert_rigid, normalized_to_pixels, pixels_to_normalized, scaled_intrinsics
from constructaide.gl import offscreen_renderer
from constructaide.modelscene import GROUND_INDEX, BimScene, MeshDict, scene_from_meshes
from schemas.messages import Intrinsics

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

_LUT_WIDTH = 4096
_NEAR_M = 0.05

_VERT = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in uint element;
layout(location = 2) in float shade;
uniform mat4 clip_from_world;
uniform mat4 camera_from_world;
uniform usampler2D visible;
flat out uint v_element;
out float v_z;
out float v_shade;
void main() {
    uint vis = element >= 16777215u ? 1u
        : texelFetch(visible, ivec2(int(element % 4096u), int(element / 4096u)), 0).r;
    v_element = element;
    v_shade = shade;
    v_z = (camera_from_world * vec4(position, 1.0)).z;
    gl_Position = vis == 0u ? vec4(2.0, 2.0, 2.0, 1.0) : clip_from_world * vec4(position, 1.0);
}
"""

_FRAG = """
#version 330 core
flat in uint v_element;
in float v_z;
in float v_shade;
layout(location = 0) out uint out_id;
layout(location = 1) out vec2 out_depth_shade;
void main() {
    out_id = v_element;
    out_depth_shade = vec2(v_z, v_shade);
}
"""


@dataclass(frozen=True)
class RasterResult:
    """Per-pixel renders at photo size (see module docstring)."""

    ids: NDArray[np.uint32]
    depth_m: NDArray[np.float32]
    shade: NDArray[np.float32]


@dataclass(frozen=True)
class RenderGeometry:
    """Undistorted render camera covering a distorted photo, and the photo->render lookup.

    ``render_intrinsics`` has no distortion; ``lookup_flat`` (H*W,) int64 indexes the render's
    flattened pixels (nearest neighbour) for every photo pixel, or is ``None`` when the photo has
    no distortion and the render is the photo grid itself. ``map_x``/``map_y`` (H, W) float32 are
    the exact render coordinates for ``cv2.remap`` (bilinear resampling of colour renders).
    ``outside`` (H, W) bool marks photo pixels whose ray the render does not cover (a strong distortion that folds
    back, or that looks beyond three times the pinhole field of view): they show nothing; None when there are none.
    """

    render_intrinsics: Intrinsics
    lookup_flat: NDArray[np.int64] | None
    map_x: NDArray[np.float32] | None = None
    map_y: NDArray[np.float32] | None = None
    outside: NDArray[np.bool_] | None = None


def projection_from_intrinsics(intr: Intrinsics, near_m: float, far_m: float) -> NDArray[np.float64]:
    """(4, 4) OpenGL clip_from_camera for an OpenCV camera; GL row ``j`` (from the bottom) = pixel row ``v = j``.

    So ``glReadPixels`` rows come out in image order without a flip.
    """
    w, h = intr.width_px, intr.height_px
    fx, fy = focal_xy(intr)
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / w
    P[0, 2] = (2.0 * intr.cx_px + 1.0) / w - 1.0
    P[1, 1] = 2.0 * fy / h
    P[1, 2] = (2.0 * intr.cy_px + 1.0) / h - 1.0
    P[2, 2] = (far_m + near_m) / (far_m - near_m)
    P[2, 3] = -2.0 * far_m * near_m / (far_m - near_m)
    P[3, 2] = 1.0
    return P


@lru_cache(maxsize=16)
def render_geometry(intr: Intrinsics, margin_px: int = 4) -> RenderGeometry:
    """Undistorted render camera and lookup table for ``intr`` (cached per Intrinsics)."""
    if intr.width_px <= 0 or intr.height_px <= 0 or intr.f_px <= 0:
        raise ValueError(f"bad intrinsics: {intr}")
    if intr.k1 == 0.0 and intr.k2 == 0.0:
        return RenderGeometry(render_intrinsics=intr, lookup_flat=None)
    w, h = intr.width_px, intr.height_px
    grid = undistorted_grid(intr)
    # per coordinate on contiguous arrays (reductions along a length-2 axis are slow at this size)
    x, y = np.ascontiguousarray(grid[..., 0]).ravel(), np.ascontiguousarray(grid[..., 1]).ravel()
    fx, fy = focal_xy(intr)
    # the canvas covers the photo's rays within three times the pinhole field of view (an estimated distortion can
    # fold the undistortion outwards); rays beyond it, or where the inversion fails, show nothing
    half = np.array([w / fx, h / fy])
    centre = np.array([intr.cx_px / fx, intr.cy_px / fy])
    lo, hi = -centre - half, -centre + 2.0 * half
    with np.errstate(invalid="ignore"):
        inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])  # False where NaN
    if not inside.any():
        raise ValueError(f"distortion k1={intr.k1}, k2={intr.k2} maps no pixel of the image to a usable ray")
    if not inside.all():
        x = np.where(inside, x, np.clip(np.nan_to_num(x, nan=0.0), lo[0], hi[0]))
        y = np.where(inside, y, np.clip(np.nan_to_num(y, nan=0.0), lo[1], hi[1]))
    xin, yin = x[inside], y[inside]
    xmin, ymin, xmax, ymax = xin.min(), yin.min(), xin.max(), yin.max()
    # Principal point on an integer pixel of the render grid.
    cx = float(np.floor(-xmin * fx) + margin_px)
    cy = float(np.floor(-ymin * fy) + margin_px)
    rw = int(np.ceil((xmax - xmin) * fx)) + 2 * margin_px + 2
    rh = int(np.ceil((ymax - ymin) * fy)) + 2 * margin_px + 2
    u, v = x * fx + cx, y * fy + cy
    ru = np.clip(np.rint(u).astype(np.int64), 0, rw - 1)
    rv = np.clip(np.rint(v).astype(np.int64), 0, rh - 1)
    r_intr = Intrinsics(width_px=rw, height_px=rh, f_px=fx, cx_px=cx, cy_px=cy, fy_over_fx=intr.fy_over_fx)
    map_x = np.where(inside, u, -1.0).astype(np.float32).reshape(h, w)
    map_y = np.where(inside, v, -1.0).astype(np.float32).reshape(h, w)
    outside = None if inside.all() else ~inside.reshape(h, w)
    return RenderGeometry(r_intr, rv * rw + ru, map_x, map_y, outside)


def undistorted_grid(intr: Intrinsics, step_px: int = 8) -> NDArray[np.float64]:
    """(H, W, 2) undistorted normalised coordinates of every photo pixel.

    Exact inversion on a grid every ``step_px`` pixels, bilinear in between (the map is smooth).
    """
    w, h = intr.width_px, intr.height_px
    gu = np.arange(0, w - 1 + step_px, step_px, dtype=np.float64)
    gv = np.arange(0, h - 1 + step_px, step_px, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    grid = pixels_to_normalized(intr, np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(len(gv), len(gu), 2)
    mu, mv = np.meshgrid(np.arange(w, dtype=np.float32) / step_px, np.arange(h, dtype=np.float32) / step_px)
    out = [cv2.remap(np.ascontiguousarray(grid[..., c], np.float32), mu, mv, cv2.INTER_LINEAR) for c in range(2)]
    return np.stack(out, axis=-1).astype(np.float64)


def scene_far_m(scene: BimScene, world_from_camera: NDArray[np.float64], extra_m: float = 0.0) -> float:
    """Far plane: distance from the camera to the farthest scene bbox corner, padded."""
    c = world_from_camera[:3, 3]
    corners = np.array(
        [
            [x, y, z]
            for x in (scene.bbox_min_m[0], scene.bbox_max_m[0])
            for y in (scene.bbox_min_m[1], scene.bbox_max_m[1])
            for z in (scene.bbox_min_m[2], scene.bbox_max_m[2])
        ]
    )
    return float(np.linalg.norm(corners - c, axis=1).max() * 1.5 + extra_m + 1.0)


def element_bounds(scene: BimScene) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Per element index (row 0 = background): bbox min (n + 1, 3), max (n + 1, 3) in metres and whether it has
    triangles (n + 1,)."""
    n = scene.num_elements
    lo = np.zeros((n + 1, 3))
    hi = np.zeros((n + 1, 3))
    counts = scene.tri_range[:, 1] - scene.tri_range[:, 0]
    has = counts > 0
    has[0] = False
    if has.any():
        starts = 3 * scene.tri_range[has, 0]
        pos = scene.positions_m.astype(np.float64)
        lo[has] = np.minimum.reduceat(pos, starts, axis=0)
        hi[has] = np.maximum.reduceat(pos, starts, axis=0)
    return lo, hi, has


def frustum_mask(
    lo: NDArray[np.float64], hi: NDArray[np.float64], clip_from_world: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """(K,) bool: the boxes ``lo``/``hi`` (K, 3) metres that may intersect the view volume of ``clip_from_world``
    (4, 4). Conservative: a box is culled only when all eight corners lie outside one clip plane."""
    corners = np.stack(
        [
            np.stack([(lo, hi)[i][:, 0], (lo, hi)[j][:, 1], (lo, hi)[k][:, 2]], axis=1)
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ],
        axis=1,
    )  # (K, 8, 3)
    clip = corners @ clip_from_world[:3, :3].T + clip_from_world[:3, 3]
    w = corners @ clip_from_world[3, :3] + clip_from_world[3, 3]
    out = np.ones(len(lo), bool)
    for axis in range(3):
        out &= ~np.all(clip[..., axis] < -w, axis=1)
        out &= ~np.all(clip[..., axis] > w, axis=1)
    return out


def draw_ranges(tri_range: NDArray[np.int64], draw: NDArray[np.bool_]) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """(first vertex, vertex count) int32 arrays of the runs of consecutive drawn elements; ``draw`` is
    (n + 1,) bool over element indices (row 0 ignored), ``tri_range`` as in :class:`BimScene`."""
    d = np.asarray(draw, bool).copy()
    d[0] = False
    edges = np.diff(np.concatenate([[0], d.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1  # inclusive element index of each run
    first = 3 * tri_range[starts, 0]
    count = 3 * (tri_range[ends, 1] - tri_range[starts, 0])
    keep = count > 0
    return first[keep].astype(np.int32), count[keep].astype(np.int32)


def vertex_array(arrays: Sequence[NDArray[np.generic]], dynamic: bool = False) -> tuple[int, list[int]]:
    """A GL vertex array with one buffer per array, attribute location = position in ``arrays``: uint32 arrays as
    integer attributes, others as float (N,) or (N, k). Returns (vao, buffers); needs a current context."""
    from OpenGL import GL

    vao = GL.glGenVertexArrays(1)
    GL.glBindVertexArray(vao)
    bufs = list(GL.glGenBuffers(len(arrays)))
    usage = GL.GL_DYNAMIC_DRAW if dynamic else GL.GL_STATIC_DRAW
    for loc, (buf, arr) in enumerate(zip(bufs, arrays, strict=True)):
        data = np.ascontiguousarray(arr)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, buf)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, max(data.nbytes, 4), data if data.size else None, usage)
        GL.glEnableVertexAttribArray(loc)
        size = data.shape[1] if data.ndim == 2 else 1
        if data.dtype == np.uint32:
            GL.glVertexAttribIPointer(loc, size, GL.GL_UNSIGNED_INT, 0, ctypes.c_void_p(0))
        else:
            GL.glVertexAttribPointer(loc, size, GL.GL_FLOAT, GL.GL_FALSE, 0, ctypes.c_void_p(0))
    GL.glBindVertexArray(0)
    return vao, bufs


class IdTarget:
    """An offscreen framebuffer kept across renders of the same size: uint32 ids at colour 0, ``channels`` (1 or
    2) float32 values at colour 1, 32-bit float depth. Use on the thread of the current GL context."""

    def __init__(self, channels: int) -> None:
        if channels not in (1, 2):
            raise ValueError("an IdTarget holds 1 or 2 value channels")
        self.channels = channels
        self.fbo = 0
        self.size = (0, 0)
        self._rbos: list[int] = []

    def bind(self, w: int, h: int) -> None:
        """Bind the (w, h) framebuffer (made, or remade at a new size, as needed)."""
        from OpenGL import GL

        if self.fbo and self.size == (w, h):
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self.fbo)
            return
        self.delete()
        self.fbo = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self.fbo)
        self._rbos = list(GL.glGenRenderbuffers(3))
        value_format = GL.GL_R32F if self.channels == 1 else GL.GL_RG32F
        for rbo, fmt, attach in zip(
            self._rbos,
            (GL.GL_R32UI, value_format, GL.GL_DEPTH_COMPONENT32F),
            (GL.GL_COLOR_ATTACHMENT0, GL.GL_COLOR_ATTACHMENT1, GL.GL_DEPTH_ATTACHMENT),
            strict=True,
        ):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rbo)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, w, h)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, attach, GL.GL_RENDERBUFFER, rbo)
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"OpenGL framebuffer incomplete ({status})")
        self.size = (w, h)

    def read(self) -> tuple[NDArray[np.uint32], NDArray[np.float32]]:
        """Ids (h, w) and values (h, w) or (h, w, 2) of the bound framebuffer, in GL row order."""
        from OpenGL import GL

        w, h = self.size
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        ids = np.empty((h, w), np.uint32)
        GL.glReadPixels(0, 0, w, h, GL.GL_RED_INTEGER, GL.GL_UNSIGNED_INT, ids)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT1)
        values = np.empty((h, w) if self.channels == 1 else (h, w, 2), np.float32)
        GL.glReadPixels(0, 0, w, h, GL.GL_RED if self.channels == 1 else GL.GL_RG, GL.GL_FLOAT, values)
        return ids, values

    def delete(self) -> None:
        """Free the framebuffer (a no-op when there is none)."""
        from OpenGL import GL

        if self.fbo:
            GL.glDeleteFramebuffers(1, [self.fbo])
            GL.glDeleteRenderbuffers(len(self._rbos), self._rbos)
        self.fbo = 0
        self.size = (0, 0)
        self._rbos = []


class GLRasterizer:
    """Headless OpenGL renderer of element ids / depth / shade; owns one EGL context.

    Create and use on a single thread. ``offscreen`` exposes the underlying
    ``pyrender.OffscreenRenderer`` so photoreal renders share the context.
    """

    def __init__(self) -> None:

        self.offscreen = offscreen_renderer(64, 64)
        self._program = 0
        self._vao = 0
        self._buffers: list[int] = []
        self._ground_vao = 0
        self._ground_buffers: list[int] = []
        self._num_vertices = 0
        self._scene: BimScene | None = None
        self._bounds: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]] | None = None
        self.last_drawn_vertices = 0
        """Vertices submitted by the last render after culling (elements hidden or outside the view skipped)."""
        self._lut_tex = 0
        self._lut_shape = (0, 0)
        self._target = IdTarget(2)
        self._last_depth_shade = np.zeros((0, 0, 2), np.float32)
        self._build_program()

    # -- GL plumbing --------------------------------------------------------------------------------

    def make_current(self) -> None:
        self.offscreen._platform.make_current()

    def _build_program(self) -> None:
        from OpenGL import GL
        from OpenGL.GL import shaders

        self.make_current()
        vs = shaders.compileShader(_VERT, GL.GL_VERTEX_SHADER)
        fs = shaders.compileShader(_FRAG, GL.GL_FRAGMENT_SHADER)
        self._program = shaders.compileProgram(vs, fs, validate=False)
        self._u_clip = GL.glGetUniformLocation(self._program, "clip_from_world")
        self._u_cam = GL.glGetUniformLocation(self._program, "camera_from_world")
        self._u_vis = GL.glGetUniformLocation(self._program, "visible")

    def _upload(self, scene: BimScene) -> None:
        from OpenGL import GL

        if self._vao:
            GL.glDeleteVertexArrays(1, [self._vao])
            GL.glDeleteBuffers(len(self._buffers), self._buffers)
        self._vao, self._buffers = vertex_array((scene.positions_m, scene.element_index, scene.shade))
        self._num_vertices = len(scene.element_index)
        rows = (scene.num_elements + 1 + _LUT_WIDTH - 1) // _LUT_WIDTH
        if self._lut_tex:
            GL.glDeleteTextures([self._lut_tex])
        self._lut_tex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._lut_tex)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage2D(
            GL.GL_TEXTURE_2D,
            0,
            GL.GL_R8UI,
            _LUT_WIDTH,
            rows,
            0,
            GL.GL_RED_INTEGER,
            GL.GL_UNSIGNED_BYTE,
            np.zeros(_LUT_WIDTH * rows, np.uint8),
        )
        self._lut_shape = (rows, _LUT_WIDTH)
        self._bounds = element_bounds(scene)
        self._scene = scene

    def _set_ground(self, scene: BimScene, ground_z_m: float, extent_m: float) -> None:
        from OpenGL import GL

        if self._ground_vao:
            GL.glDeleteVertexArrays(1, [self._ground_vao])
            GL.glDeleteBuffers(len(self._ground_buffers), self._ground_buffers)
        c = 0.5 * (scene.bbox_min_m + scene.bbox_max_m)
        x0, x1, y0, y1 = c[0] - extent_m, c[0] + extent_m, c[1] - extent_m, c[1] + extent_m
        quad = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y0], [x1, y1], [x0, y1]], np.float64)
        pos = np.column_stack([quad, np.full(6, ground_z_m)]).astype(np.float32)
        self._ground_vao, self._ground_buffers = vertex_array(
            (pos, np.full(6, GROUND_INDEX, np.uint32), np.full(6, 0.5, np.float32))
        )

    # -- rendering ----------------------------------------------------------------------------------

    def render_undistorted(
        self,
        scene: BimScene,
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        visible: NDArray[np.bool_],
        ground_z_m: float | None = None,
    ) -> RasterResult:
        """Render with an undistorted ``intr`` (k1, k2 ignored). ``visible`` is (num_elements + 1,) bool."""
        from OpenGL import GL

        if visible.shape != (scene.num_elements + 1,):
            raise ValueError(f"visible mask has shape {visible.shape}, expected ({scene.num_elements + 1},)")
        self.make_current()
        if self._scene is not scene:
            self._upload(scene)
        w, h = intr.width_px, intr.height_px
        ground_extent = 0.0
        if ground_z_m is not None:
            ground_extent = 4.0 * float(np.max(scene.bbox_max_m - scene.bbox_min_m)) + 50.0
            self._set_ground(scene, ground_z_m, ground_extent)
        far = scene_far_m(scene, world_from_camera, 2.0 * ground_extent)
        camera_from_world = invert_rigid(np.asarray(world_from_camera, np.float64))
        clip_from_world = projection_from_intrinsics(intr, _NEAR_M, far) @ camera_from_world

        lut = np.zeros(self._lut_shape[0] * self._lut_shape[1], np.uint8)
        lut[: len(visible)] = visible
        lut[0] = 0
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._lut_tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexSubImage2D(
            GL.GL_TEXTURE_2D,
            0,
            0,
            0,
            self._lut_shape[1],
            self._lut_shape[0],
            GL.GL_RED_INTEGER,
            GL.GL_UNSIGNED_BYTE,
            lut,
        )

        self._target.bind(w, h)
        GL.glDrawBuffers(2, [GL.GL_COLOR_ATTACHMENT0, GL.GL_COLOR_ATTACHMENT1])
        GL.glViewport(0, 0, w, h)
        GL.glDisable(GL.GL_MULTISAMPLE)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glClearBufferuiv(GL.GL_COLOR, 0, np.zeros(4, np.uint32))
        GL.glClearBufferfv(GL.GL_COLOR, 1, np.zeros(4, np.float32))
        GL.glClearBufferfv(GL.GL_DEPTH, 0, np.ones(1, np.float32))
        GL.glUseProgram(self._program)
        GL.glUniformMatrix4fv(self._u_clip, 1, GL.GL_TRUE, clip_from_world.astype(np.float32))
        GL.glUniformMatrix4fv(self._u_cam, 1, GL.GL_TRUE, camera_from_world.astype(np.float32))
        GL.glUniform1i(self._u_vis, 0)
        self.last_drawn_vertices = 0
        if self._num_vertices and self._bounds is not None:
            # Culling: only runs of elements that are visible and whose bbox meets the view volume are submitted
            # (the soup is ordered by element; the visibility texture still decides per vertex).
            lo, hi, has = self._bounds
            draw = visible & has
            draw[draw] = frustum_mask(lo[draw], hi[draw], clip_from_world)
            first, count = draw_ranges(scene.tri_range, draw)
            if len(first):
                GL.glBindVertexArray(self._vao)
                if len(first) == 1:
                    GL.glDrawArrays(GL.GL_TRIANGLES, int(first[0]), int(count[0]))
                else:
                    GL.glMultiDrawArrays(GL.GL_TRIANGLES, first, count, len(first))
                self.last_drawn_vertices = int(count.sum())
        if ground_z_m is not None:
            GL.glBindVertexArray(self._ground_vao)
            GL.glDrawArrays(GL.GL_TRIANGLES, 0, 6)
        GL.glBindVertexArray(0)
        GL.glUseProgram(0)

        ids, zs = self._target.read()
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        self._last_depth_shade = zs
        return RasterResult(ids=ids, depth_m=zs[..., 0], shade=zs[..., 1])

    def render(
        self,
        scene: BimScene,
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        visible: NDArray[np.bool_] | None = None,
        ground_z_m: float | None = None,
    ) -> RasterResult:
        """Render at photo size with the photo's lens distortion (see module docstring).

        ``visible`` (num_elements + 1,) bool selects drawn elements (default all);
        ``ground_z_m`` adds an opaque ground plane (index :data:`GROUND_INDEX`) at that height.
        """
        if visible is None:
            visible = np.ones(scene.num_elements + 1, bool)
        geo = render_geometry(intr)
        raw = self.render_undistorted(scene, geo.render_intrinsics, world_from_camera, visible, ground_z_m)
        if geo.lookup_flat is None:
            return raw
        shape = (intr.height_px, intr.width_px)
        idx = geo.lookup_flat
        zs = self._last_depth_shade.reshape(-1, 2)[idx].reshape(*shape, 2)
        ids = raw.ids.ravel()[idx].reshape(shape)
        if geo.outside is not None:
            ids[geo.outside] = 0
            zs[geo.outside] = 0.0
        return RasterResult(ids=ids, depth_m=zs[..., 0], shade=zs[..., 1])

    def close(self) -> None:
        """Free this rasterizer's GL objects and its EGL context (call on the owning thread; the process-wide EGL
        display stays, see :mod:`constructaide.gl`)."""
        from OpenGL import GL

        try:
            self.make_current()
            if self._vao:
                GL.glDeleteVertexArrays(1, [self._vao])
                GL.glDeleteBuffers(len(self._buffers), self._buffers)
            self._target.delete()
            if self._lut_tex:
                GL.glDeleteTextures([self._lut_tex])
        except Exception:  # context already gone (interpreter exit)
            pass
        with contextlib.suppress(Exception):
            self.offscreen.delete()  # only this context (constructaide.gl keeps the shared EGL display)
        self._vao = self._lut_tex = 0
        self._scene = None
        self._target = IdTarget(2)


# -- surface maps and depth lookups on top of the rasterizer ----------------------------------------


@dataclass
class ModelMaps:
    """Per-pixel model geometry for one camera at one image size (h, w).

    ``depth_m``: float32 camera z in metres, ``inf`` where no model; ``normal_in_world``: float32 (h, w, 3) unit
    normals (zero where no model), oriented towards the camera; ``point_in_world_m``: float32 (h, w, 3) surface
    points (NaN where no model).
    """

    depth_m: NDArray[np.float32]
    normal_in_world: NDArray[np.float32]
    point_in_world_m: NDArray[np.float32]

    @property
    def has_model(self) -> NDArray[np.bool_]:
        return np.isfinite(self.depth_m)


def normals_from_depth(depth_m: NDArray[np.float32], intr: Intrinsics) -> tuple[NDArray[np.float32], ...]:
    """Camera-frame points (h, w, 3) and unit normals (h, w, 3) of a pinhole depth map (``inf`` = no surface).

    Normals are the cross product of one-sided differences, each taken on the side with the smaller depth jump
    (depth edges do not smear; exact on planar faces), and face the camera; pixels without depth get NaN points
    and zero normals.
    """
    h, w = depth_m.shape
    fx, fy = focal_xy(intr)
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    z = depth_m.astype(np.float32)
    with np.errstate(invalid="ignore"):  # 0 * inf on the principal point's row and column where no surface
        pts = np.stack([(u - intr.cx_px) / fx * z, (v - intr.cy_px) / fy * z, z], axis=-1)
    pts[~np.isfinite(z)] = np.nan

    def one_sided(axis: int) -> NDArray[np.float32]:
        fwd = np.roll(pts, -1, axis=axis) - pts
        bwd = pts - np.roll(pts, 1, axis=axis)
        fz = np.abs(fwd[..., 2])
        bz = np.abs(bwd[..., 2])
        fz = np.where(np.isfinite(fz), fz, np.inf)
        bz = np.where(np.isfinite(bz), bz, np.inf)
        return np.where((fz <= bz)[..., None], fwd, bwd)

    n = np.cross(one_sided(1), one_sided(0))
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    n[np.sum(n * pts, axis=-1) > 0] *= -1.0  # towards the camera at the origin: n . p < 0
    n[~np.isfinite(n).all(axis=-1)] = 0.0
    return pts.astype(np.float32), n.astype(np.float32)


def _pinhole(intr: Intrinsics) -> Intrinsics:
    """The same camera without lens distortion."""
    return msgspec.structs.replace(intr, k1=0.0, k2=0.0)


class ModelView:
    """A set of meshes (site-local metres, z up) seen from any camera: rasters, surface maps, depth lookups.

    ``elements`` arguments name the meshes drawn (None: all); ``ground_z_m`` adds an opaque horizontal ground
    plane at that height (None: none). One :class:`GLRasterizer`, created on the first render; call a view from
    one thread only (the EGL context is bound to it).
    """

    def __init__(self, meshes: MeshDict | BimScene) -> None:
        self._ras: GLRasterizer | None = None
        self.scene = meshes if isinstance(meshes, BimScene) else scene_from_meshes(meshes)

    @property
    def empty(self) -> bool:
        return self.scene.num_triangles == 0

    def set_meshes(self, meshes: MeshDict | BimScene) -> None:
        """Replace the meshes (the GL context is kept)."""
        self.scene = meshes if isinstance(meshes, BimScene) else scene_from_meshes(meshes)

    @property
    def rasterizer(self) -> GLRasterizer:
        if self._ras is None:
            self._ras = GLRasterizer()
        return self._ras

    def visible(self, elements: set[str] | frozenset[str] | None = None) -> NDArray[np.bool_]:
        """(num_elements + 1,) bool for :meth:`GLRasterizer.render`: the named elements (all when None)."""
        vis = np.ones(self.scene.num_elements + 1, bool)
        if elements is not None:
            vis[1:] = [g in elements for g in self.scene.global_ids]
        vis[0] = False
        return vis

    def raster(
        self,
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        elements: set[str] | frozenset[str] | None = None,
        ground_z_m: float | None = None,
    ) -> RasterResult:
        """Element ids, depth and shade at the photo's size with its lens distortion (see :class:`RasterResult`)."""
        wfc = np.asarray(world_from_camera, np.float64).reshape(4, 4)
        return self.rasterizer.render(self.scene, intr, wfc, self.visible(elements), ground_z_m)

    def depth_map(
        self,
        world_from_camera: NDArray[np.float64],
        intr: Intrinsics,
        elements: set[str] | frozenset[str] | None = None,
        ground_z_m: float | None = None,
    ) -> NDArray[np.float32]:
        """(H, W) float32 camera-z depth (m) of the undistorted pinhole camera of ``intr`` (k1, k2 ignored); 0 where
        nothing is hit."""
        wfc = np.asarray(world_from_camera, np.float64).reshape(4, 4)
        res = self.rasterizer.render_undistorted(self.scene, _pinhole(intr), wfc, self.visible(elements), ground_z_m)
        return np.ascontiguousarray(res.depth_m, np.float32)

    def depth_at(
        self,
        world_from_camera: NDArray[np.float64],
        intr: Intrinsics,
        pixels_px: NDArray[np.float64],
        elements: set[str] | frozenset[str] | None = None,
        ground_z_m: float | None = None,
        max_relative_spread: float = 0.03,
    ) -> NDArray[np.float64]:
        """(N,) camera-z depth (m) of the model at distorted pixels (N, 2) of a photo; NaN where nothing is hit,
        outside the image, or on a depth discontinuity (the 3x3 neighbourhood's spread above
        ``max_relative_spread`` of the depth: a silhouette pixel does not take the background's depth)."""
        px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
        out = np.full(len(px), np.nan)
        if len(px) == 0:
            return out
        pinhole = _pinhole(intr)
        depth = self.depth_map(world_from_camera, pinhole, elements, ground_z_m)
        lo = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32), np.ones((3, 3), np.uint8))
        hi = cv2.dilate(depth, np.ones((3, 3), np.uint8))
        uv = np.round(normalized_to_pixels(pinhole, pixels_to_normalized(intr, px))).astype(int)
        h, w = depth.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        u, v = uv[inside, 0], uv[inside, 1]
        d, d_lo, d_hi = depth[v, u], lo[v, u], hi[v, u]
        ok = (d > 0) & np.isfinite(d_lo) & (d_hi - d_lo <= max_relative_spread * d)
        out[np.nonzero(inside)[0]] = np.where(ok, d, np.nan)
        return out

    def maps(
        self,
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        width_px: int,
        height_px: int,
        elements: set[str] | frozenset[str] | None = None,
        ground_z_m: float | None = None,
    ) -> ModelMaps:
        """Depth, normals and world points of the model for a camera (full-resolution ``intr``) at image size
        (width_px, height_px), lens distortion included (normals from the undistorted render's depth)."""
        target = scaled_intrinsics(intr, width_px, height_px)
        wfc = np.asarray(world_from_camera, np.float64).reshape(4, 4)
        if self.empty:
            return ModelMaps(
                np.full((height_px, width_px), np.inf, np.float32),
                np.zeros((height_px, width_px, 3), np.float32),
                np.full((height_px, width_px, 3), np.nan, np.float32),
            )
        geo = render_geometry(target)
        res = self.rasterizer.render_undistorted(
            self.scene, geo.render_intrinsics, wfc, self.visible(elements), ground_z_m
        )
        depth_pin = np.where(res.depth_m > 0, res.depth_m, np.inf).astype(np.float32)
        pts_cam, n_cam = normals_from_depth(depth_pin, geo.render_intrinsics)
        if geo.lookup_flat is not None:
            pts_cam = pts_cam.reshape(-1, 3)[geo.lookup_flat].reshape(height_px, width_px, 3)
            n_cam = n_cam.reshape(-1, 3)[geo.lookup_flat].reshape(height_px, width_px, 3)
            if geo.outside is not None:
                pts_cam[geo.outside] = np.nan
                n_cam[geo.outside] = 0.0
        depth = pts_cam[..., 2].copy()
        depth[~np.isfinite(depth)] = np.inf
        R = wfc[:3, :3].astype(np.float32)
        t = wfc[:3, 3].astype(np.float32)
        return ModelMaps(depth.astype(np.float32), (n_cam @ R.T).astype(np.float32), (pts_cam @ R.T + t))

    def close(self) -> None:
        """Free the GL objects and context (call on the rendering thread)."""
        if self._ras is not None:
            self._ras.close()
            self._ras = None
