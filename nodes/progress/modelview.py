"""Element-ID and depth layers of the BIM seen by a registered camera (OpenGL 3.3 on EGL, headless).

For a camera and two element sets — ``built`` (what is believed to stand) and ``candidates`` (what may have
been built since) — one call draws three passes into an integer ID target without multisampling (ids stay exact):

* ``built``: the front-most built element per pixel (``ids_built``, ``depth_built_m``);
* ``front``: the front-most candidate *in front of* the built surface (``ids_front``, ``depth_front_m``): what the
  pixel would show if that candidate stood;
* ``second``: the next candidate behind it, still in front of the built surface (``ids_second``): a pixel whose
  second id is 0 can only change through its front candidate.

Ids are 1-based element indices (0 = none); depths are camera-frame z in metres, ``inf`` where nothing is drawn.
The scene is drawn into an undistorted canvas covering the distorted photo and resampled (nearest) onto its
pixel grid through :mod:`constructaide.camera`'s radial model. Create and use a :class:`LayerRenderer` on one
thread (the EGL context is thread-bound).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from constructaide.camera import invert_rigid, pixels_to_normalized
from constructaide.gl import offscreen_renderer
from constructaide.modelscene import build_scene
from constructaide.modelview import IdTarget, projection_from_intrinsics, render_geometry, vertex_array
from schemas.messages import BimElement, Intrinsics

Mesh = tuple[NDArray[np.float64], NDArray[np.int32]]
_NEAR_M = 0.05

_VERT = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in uint element;
layout(location = 2) in uint code;
uniform mat4 clip_from_world;
uniform mat4 camera_from_world;
uniform uint draw_code;
flat out uint v_element;
out float v_z;
void main() {
    v_element = element;
    v_z = (camera_from_world * vec4(position, 1.0)).z;
    gl_Position = code == draw_code ? clip_from_world * vec4(position, 1.0) : vec4(2.0, 2.0, 2.0, 1.0);
}
"""

_FRAG = """
#version 330 core
flat in uint v_element;
in float v_z;
uniform usampler2D front_ids;
uniform bool skip_front;
layout(location = 0) out uint out_id;
layout(location = 1) out float out_z;
void main() {
    if (skip_front && texelFetch(front_ids, ivec2(gl_FragCoord.xy), 0).r == v_element) discard;
    out_id = v_element;
    out_z = v_z;
}
"""


@dataclass(frozen=True)
class Layers:
    """Per-pixel layers at photo (or working) size; see the module docstring."""

    ids_built: NDArray[np.uint32]
    depth_built_m: NDArray[np.float32]
    ids_front: NDArray[np.uint32]
    depth_front_m: NDArray[np.float32]
    ids_second: NDArray[np.uint32]

    @property
    def ids_all(self) -> NDArray[np.uint32]:
        """Front-most element of built + candidates."""
        return np.where(self.ids_front > 0, self.ids_front, self.ids_built)

    @property
    def depth_all_m(self) -> NDArray[np.float32]:
        return np.minimum(self.depth_front_m, self.depth_built_m)


def surface_height_m(
    layers: Layers, intr: Intrinsics, world_from_camera: NDArray[np.float64], where: NDArray[np.bool_] | None = None
) -> NDArray[np.float32]:
    """(H, W) world z in metres of the surface each pixel of ``layers`` shows (front-most of built + candidates;
    NaN where nothing is drawn, and outside ``where`` when given); ``intr`` at the layers' size, radial distortion
    undone."""
    depth = np.where(layers.ids_front > 0, layers.depth_front_m, layers.depth_built_m)
    sel = np.isfinite(depth) if where is None else where & np.isfinite(depth)
    vs, us = np.nonzero(sel)
    xy = pixels_to_normalized(intr, np.stack([us, vs], axis=1), iterations=8)  # contracts by ~|2 k1 r^2| a step
    T = np.asarray(world_from_camera, np.float64)
    d = depth[vs, us].astype(np.float64)
    out = np.full(depth.shape, np.nan, np.float32)
    out[vs, us] = T[2, 3] + d * (T[2, 0] * xy[:, 0] + T[2, 1] * xy[:, 1] + T[2, 2])
    return out


def below_terrain(
    layers: Layers,
    intr: Intrinsics,
    world_from_camera: NDArray[np.float64],
    terrain_height_m: float,
    margin_m: float,
    reaches_below: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """(H, W) pixels whose element surface lies more than ``margin_m`` below the site's terrain (the ground, not in
    the model, stands in front of it: a backfilled footing or basement wall shows soil whether it stands or not).
    ``reaches_below`` (n + 1,) per element index: whether any of it lies that low (its box); only their pixels are
    looked at. The occlude node marks the same pixels of its own render as static occluders."""
    owner = layers.ids_all.astype(np.int64)
    where = owner > 0 if reaches_below is None else np.asarray(reaches_below, bool)[owner] & (owner > 0)
    if not where.any():
        return np.zeros(owner.shape, bool)
    z = surface_height_m(layers, intr, world_from_camera, where)
    with np.errstate(invalid="ignore"):
        return np.isfinite(z) & (z < terrain_height_m - margin_m)


class LayerRenderer:
    """Draws :class:`Layers` of one model (see :meth:`set_model`) for any camera; owns one EGL context."""

    def __init__(self) -> None:
        self._gl: Any = None
        self._program = 0
        self._vao = 0
        self._buffers: list[int] = []
        self._target = IdTarget(1)
        self._front_tex = 0
        self._elements = np.zeros(0, np.uint32)
        self._bbox = (np.zeros(3), np.zeros(3))
        self.num_elements = 0

    # -- GL plumbing --------------------------------------------------------------------------------

    def _current(self) -> None:
        from OpenGL import GL
        from OpenGL.GL import shaders

        if self._gl is None:
            self._gl = offscreen_renderer(64, 64)
            self._gl._platform.make_current()
            vs = shaders.compileShader(_VERT, GL.GL_VERTEX_SHADER)
            fs = shaders.compileShader(_FRAG, GL.GL_FRAGMENT_SHADER)
            self._program = shaders.compileProgram(vs, fs, validate=False)
            self._u = {
                n: GL.glGetUniformLocation(self._program, n)
                for n in ("clip_from_world", "camera_from_world", "draw_code", "front_ids", "skip_front")
            }
            self._front_tex = GL.glGenTextures(1)
        self._gl._platform.make_current()

    def set_model(self, global_ids: list[str], meshes: Mapping[str, Mesh]) -> None:
        """Upload the meshes of ``global_ids`` (index i + 1 = ``global_ids[i]``)."""
        from OpenGL import GL

        self._current()
        scene = build_scene([BimElement(global_id=g, ifc_class="", geometry_ref=g) for g in global_ids], meshes)
        positions, elements = scene.positions_m, scene.element_index
        if self._vao:
            GL.glDeleteVertexArrays(1, [self._vao])
            GL.glDeleteBuffers(len(self._buffers), self._buffers)
        codes = np.zeros(len(elements), np.uint32)
        self._vao, self._buffers = vertex_array((positions, elements, codes), dynamic=True)
        self._elements = elements
        self.num_elements = len(global_ids)
        self._bbox = (positions.min(0), positions.max(0)) if len(positions) else (np.zeros(3), np.zeros(3))

    def _pass(
        self, skip_front: bool, draws: tuple[tuple[int, bool], ...] = ((1, False), (2, True))
    ) -> tuple[NDArray[np.uint32], NDArray[np.float32]]:
        """Cleared targets, then each ``(code, colour)`` of ``draws`` in turn: the elements of that code into depth,
        and into ids + z when ``colour`` (default: built into depth only, then candidates); returns (ids, z) in GL
        row order."""
        from OpenGL import GL

        GL.glClearBufferuiv(GL.GL_COLOR, 0, np.zeros(4, np.uint32))
        GL.glClearBufferfv(GL.GL_COLOR, 1, np.full(4, np.inf, np.float32))
        GL.glClearBufferfv(GL.GL_DEPTH, 0, np.ones(1, np.float32))
        n = len(self._elements)
        GL.glUniform1i(self._u["skip_front"], int(skip_front))
        for code, colour in draws:
            GL.glColorMask(colour, colour, colour, colour)
            GL.glUniform1ui(self._u["draw_code"], code)
            GL.glDrawArrays(GL.GL_TRIANGLES, 0, n)
        GL.glColorMask(True, True, True, True)
        return self._target.read()

    # -- rendering ----------------------------------------------------------------------------------

    def render(
        self,
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        built: NDArray[np.bool_],
        candidates: NDArray[np.bool_],
    ) -> Layers:
        """Layers at ``intr``'s size. ``built`` and ``candidates`` are (num_elements + 1,) bool (row 0 unused);
        an element in both counts as built."""
        from OpenGL import GL

        if built.shape != (self.num_elements + 1,) or candidates.shape != built.shape:
            raise ValueError(f"element masks must have shape ({self.num_elements + 1},)")
        self._current()
        code_of = np.where(built, 1, np.where(candidates, 2, 0)).astype(np.uint32)
        codes = np.ascontiguousarray(code_of[self._elements])
        geo = render_geometry(intr, margin_px=2)
        canvas, lookup = geo.render_intrinsics, geo.lookup_flat
        w, h = canvas.width_px, canvas.height_px
        camera_from_world = invert_rigid(np.asarray(world_from_camera, np.float64))
        lo, hi = self._bbox
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        far = float(np.linalg.norm(corners - world_from_camera[:3, 3], axis=1).max() * 1.5 + 1.0)
        clip_from_world = projection_from_intrinsics(canvas, _NEAR_M, far) @ camera_from_world

        self._target.bind(w, h)
        GL.glUseProgram(self._program)
        GL.glBindVertexArray(self._vao)
        if codes.size:
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._buffers[2])
            GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, codes.nbytes, codes)
        GL.glDrawBuffers(2, [GL.GL_COLOR_ATTACHMENT0, GL.GL_COLOR_ATTACHMENT1])
        GL.glViewport(0, 0, w, h)
        for cap in (GL.GL_MULTISAMPLE, GL.GL_BLEND, GL.GL_CULL_FACE):
            GL.glDisable(cap)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glUniformMatrix4fv(self._u["clip_from_world"], 1, GL.GL_TRUE, clip_from_world.astype(np.float32))
        GL.glUniformMatrix4fv(self._u["camera_from_world"], 1, GL.GL_TRUE, camera_from_world.astype(np.float32))
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        ids_b, z_b = self._pass(skip_front=False, draws=((1, True),))  # built alone
        ids_f, z_f = self._pass(skip_front=False)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._front_tex)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_R32UI, w, h, 0, GL.GL_RED_INTEGER, GL.GL_UNSIGNED_INT, ids_f)
        GL.glUniform1i(self._u["front_ids"], 0)
        ids_s, _ = self._pass(skip_front=True)
        GL.glBindVertexArray(0)
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        out = [ids_b, z_b, ids_f, z_f, ids_s]
        if lookup is not None:
            shape = (intr.height_px, intr.width_px)
            out = [a.ravel()[lookup].reshape(shape) for a in out]
            if geo.outside is not None:  # rays the canvas does not cover show nothing
                for a, empty in zip(out, (0, np.inf, 0, np.inf, 0), strict=True):
                    a[geo.outside] = empty
        return Layers(
            out[0].astype(np.uint32),
            out[1].astype(np.float32),
            out[2].astype(np.uint32),
            out[3].astype(np.float32),
            out[4].astype(np.uint32),
        )

    def close(self) -> None:
        """Free GL objects (on the owning thread). The EGL display stays for the process (see constructaide.gl)."""
        if self._gl is None:
            return
        from OpenGL import GL

        try:
            self._gl._platform.make_current()
            if self._vao:
                GL.glDeleteVertexArrays(1, [self._vao])
                GL.glDeleteBuffers(len(self._buffers), self._buffers)
            self._target.delete()
            GL.glDeleteTextures([self._front_tex])
        except Exception:  # context already gone at interpreter exit
            pass
        self._vao = 0
        self._target = IdTarget(1)
