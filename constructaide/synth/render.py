"""Headless rendering of the site with pyrender (EGL): colour, element IDs, depth and occluder masks.

Every photo is rendered undistorted with a margin, then resampled through the radial model of
``constructaide.camera`` so photo, IDs, depth and masks are aligned pixel for pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pyrender
from numpy.typing import NDArray

from constructaide.camera import undistort_normalized
from constructaide.gl import offscreen_renderer
from schemas.messages import Intrinsics

from .building import Building, Element
from .scene import Solid
from .textures import TEXTURE_TILE_M

F64 = NDArray[np.float64]

CAT_NONE, CAT_ELEMENT, CAT_STATIC, CAT_DYNAMIC = 0, 1, 2, 3
Z_NEAR_M, Z_FAR_M = 0.25, 1500.0
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Lighting:
    """Per-photo lighting: unit vector towards the sun (site frame), intensities, sky colours (RGB 0-255)."""

    sun_dir_world: F64
    sun_intensity: float
    ambient: float
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    exposure: float
    cloud_seed: int
    cloudiness: float


@dataclass
class RenderResult:
    """All arrays at photo resolution (H, W): color uint8 (H, W, 3) RGB; element_index uint16 (0 = none);
    depth_m float32 z-depth (0 = sky); static_mask / dynamic_mask bool."""

    color: NDArray[np.uint8]
    element_index: NDArray[np.uint16]
    depth_m: NDArray[np.float32]
    static_mask: NDArray[np.bool_]
    dynamic_mask: NDArray[np.bool_]


def _planar_uv(tri_vertices: F64, tile: tuple[float, float]) -> F64:
    """UVs (3 per triangle) by projecting onto the plane of the dominant normal axis (v up = world up / north;
    pyrender uploads texture rows bottom-up, so image row 0 is the top of a wall)."""
    v = tri_vertices.reshape(-1, 3, 3)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    axis = np.argmax(np.abs(n), axis=1)
    sign = np.sign(n[np.arange(len(n)), axis])
    sign[sign == 0] = 1
    uv = np.zeros((len(v), 3, 2))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    s = sign[:, None]
    uv[..., 0] = np.where((axis == 0)[:, None], y * s, np.where((axis == 1)[:, None], -x * s, x))
    uv[..., 1] = np.where((axis == 2)[:, None], y, z)
    uv[..., 0] /= tile[0]
    uv[..., 1] /= tile[1]
    return uv.reshape(-1, 2)


def _triangles(polygons: list[list[int]]) -> NDArray[np.int64]:
    return np.asarray([[p[0], p[i], p[i + 1]] for p in polygons for i in range(1, len(p) - 1)], dtype=np.int64)


def _primitive(
    vertices_m: F64,
    polygons: list[list[int]],
    material: pyrender.Material,
    texture_key: str,
    uv_mode: str,
    site_extent_m: float,
) -> pyrender.Primitive:
    tris = _triangles(polygons)
    pos = vertices_m[tris].reshape(-1, 3)
    a, b, c = pos[0::3], pos[1::3], pos[2::3]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    normals = np.repeat(n, 3, axis=0)
    if uv_mode == "site":
        uv = np.stack(
            [(pos[:, 0] + site_extent_m / 2) / site_extent_m, (pos[:, 1] + site_extent_m / 2) / site_extent_m], 1
        )
    else:
        uv = _planar_uv(pos, TEXTURE_TILE_M[texture_key])
    idx = np.arange(len(pos), dtype=np.uint32).reshape(-1, 3)
    return pyrender.Primitive(
        positions=pos.astype(np.float32),
        normals=normals.astype(np.float32),
        texcoord_0=uv.astype(np.float32),
        indices=idx,
        material=material,
    )


def undistortion_maps(intr: Intrinsics, step_px: int = 8) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Undistorted normalised coordinates (x, y), each (H, W), of every photo pixel.

    Exact (fixed-point inversion of ``constructaide.camera``'s model) on a grid every ``step_px`` pixels and
    bilinear in between; the map is smooth, so the interpolation error is ~0.01 px (less for longer focals).
    """
    W, H = intr.width_px, intr.height_px
    gu = np.arange(0, W - 1 + step_px, step_px, dtype=np.float64)
    gv = np.arange(0, H - 1 + step_px, step_px, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    xy_d = (np.stack([uu.ravel(), vv.ravel()], 1) - np.array([intr.cx_px, intr.cy_px])) / intr.f_px
    xy = undistort_normalized(xy_d, intr.k1, intr.k2, iterations=30).reshape(len(gv), len(gu), 2)
    u, v = np.meshgrid(np.arange(W, dtype=np.float32) / step_px, np.arange(H, dtype=np.float32) / step_px)
    # Bilinear with align-corners semantics; u / step has a fractional part in multiples of 1 / step_px, which
    # OpenCV's 1/32 px interpolation weights represent exactly.
    out = [cv2.remap(np.ascontiguousarray(xy[..., c], dtype=np.float32), u, v, cv2.INTER_LINEAR) for c in range(2)]
    return out[0].astype(np.float64), out[1].astype(np.float64)


class SiteRenderer:
    """Owns one pyrender scene and one OffscreenRenderer; renders photos of any camera at any date."""

    def __init__(
        self,
        building: Building,
        element_index: dict[str, int],
        static: list[Solid],
        dynamic: list[Solid],
        textures: dict[str, NDArray[np.uint8]],
        site_extent_m: float,
        rng: np.random.Generator,
    ) -> None:
        self.scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.3, 0.3, 0.3])
        sampler = pyrender.Sampler(magFilter=9729, minFilter=9987, wrapS=10497, wrapT=10497)
        clamp = pyrender.Sampler(magFilter=9729, minFilter=9987, wrapS=33071, wrapT=33071)
        self._tex = {
            k: pyrender.Texture(source=v, source_channels="RGB", sampler=clamp if k == "site_ground" else sampler)
            for k, v in textures.items()
        }
        self._insertion_order: list[pyrender.Node] = []
        self.element_nodes: dict[str, pyrender.Node] = {}
        self.seg_colors: dict[pyrender.Node, tuple[int, int, int]] = {}
        self.static_nodes: list[pyrender.Node] = []
        self.dynamic_nodes: dict[str, pyrender.Node] = {}
        tex_of = {"concrete": "concrete", "brick": "brick", "glass": "glass", "steel": "steel", "roof": "roof"}
        for e in building.elements:
            tint = float(rng.uniform(0.88, 1.08))
            mat = self._material(tex_of[e.material], tint, metallic=0.3 if e.material in ("glass", "steel") else 0.0)
            node = self._add(e.key, e.vertices_m, e.polygons, mat, tex_of[e.material], "planar", site_extent_m)
            idx = element_index[e.key]
            self.element_nodes[e.key] = node
            self.seg_colors[node] = (idx & 255, idx >> 8, CAT_ELEMENT)
        for s in static:
            node = self._add(
                s.name, s.vertices_m, s.polygons, self._material(s.texture, 1.0), s.texture, s.uv_mode, site_extent_m
            )
            self.static_nodes.append(node)
            self.seg_colors[node] = (0, 0, CAT_STATIC)
        for s in dynamic:
            node = self._add(
                s.name, s.vertices_m, s.polygons, self._material(s.texture, 1.0), s.texture, "planar", site_extent_m
            )
            self.dynamic_nodes[s.name] = node
            self.seg_colors[node] = (0, 0, CAT_DYNAMIC)
        self.sun = pyrender.DirectionalLight(color=np.ones(3), intensity=3.0)
        self.sun_node = self.scene.add(self.sun, pose=np.eye(4))
        self.camera_node: pyrender.Node | None = None
        self.renderer = offscreen_renderer(64, 64)
        # pyrender draws meshes in set order (memory addresses) and ties at shared edges go to the first drawn:
        # fix the order to insertion order so renders are byte-identical across runs.
        order = {n: i for i, n in enumerate(self._insertion_order)}
        self.renderer._renderer._sorted_mesh_nodes = lambda scene: sorted(scene.mesh_nodes, key=order.__getitem__)
        self._sky_rng_cache: dict[int, NDArray[np.float32]] = {}

    def _material(self, tex: str, tint: float, metallic: float = 0.0) -> pyrender.MetallicRoughnessMaterial:
        return pyrender.MetallicRoughnessMaterial(
            baseColorTexture=self._tex[tex],
            baseColorFactor=[tint, tint, tint, 1.0],
            metallicFactor=metallic,
            roughnessFactor=0.85,
            doubleSided=False,
        )

    def _add(
        self,
        name: str,
        vertices_m: F64,
        polygons: list[list[int]],
        mat: pyrender.Material,
        tex: str,
        uv_mode: str,
        site_extent_m: float,
    ) -> pyrender.Node:
        mesh = pyrender.Mesh([_primitive(vertices_m, polygons, mat, tex, uv_mode, site_extent_m)], name=name)
        node = self.scene.add(mesh, name=name)
        self._insertion_order.append(node)
        return node

    def close(self) -> None:
        self.renderer.delete()

    # -- one photo -------------------------------------------------------------------------------------------
    def render(
        self,
        intr: Intrinsics,
        world_from_camera: F64,
        built: set[str],
        dynamic_poses: dict[str, F64 | None],
        lighting: Lighting,
        noise_rng: np.random.Generator,
    ) -> RenderResult:
        """Render one photo. ``built``: element keys present; ``dynamic_poses``: world pose or None per object."""
        xy_x, xy_y = undistortion_maps(intr)
        f = intr.f_px
        half_w = math.ceil(np.abs(xy_x).max() * f) + 2
        half_h = math.ceil(np.abs(xy_y).max() * f) + 2
        Wr, Hr = 2 * half_w + 1, 2 * half_h + 1
        cxr, cyr = float(half_w), float(half_h)
        map_x = (xy_x * f + cxr).astype(np.float32)
        map_y = (xy_y * f + cyr).astype(np.float32)

        for key, node in self.element_nodes.items():
            node.mesh.is_visible = key in built
        for key, node in self.dynamic_nodes.items():
            pose = dynamic_poses.get(key)
            node.mesh.is_visible = pose is not None
            if pose is not None:
                self.scene.set_pose(node, pose)
        cam = pyrender.IntrinsicsCamera(f, f, cxr + 0.5, cyr + 0.5, znear=Z_NEAR_M, zfar=Z_FAR_M)
        if self.camera_node is not None:
            self.scene.remove_node(self.camera_node)
        self.camera_node = self.scene.add(cam, pose=world_from_camera @ _GL_FROM_CV)
        s = lighting.sun_dir_world
        z = s / np.linalg.norm(s)
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
        sun_pose = np.eye(4)
        sun_pose[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        self.scene.set_pose(self.sun_node, sun_pose)
        self.sun.intensity = lighting.sun_intensity
        self.scene.ambient_light = np.full(3, lighting.ambient)
        self.renderer.viewport_width, self.renderer.viewport_height = Wr, Hr

        color, depth = self.renderer.render(self.scene)
        visible = {n: c for n, c in self.seg_colors.items() if n.mesh.is_visible}
        seg, _ = self.renderer.render(self.scene, flags=pyrender.RenderFlags.SEG, seg_node_map=visible)
        bim_only = {n: c for n, c in visible.items() if c[2] == CAT_ELEMENT}
        seg_bim, _ = self.renderer.render(self.scene, flags=pyrender.RenderFlags.SEG, seg_node_map=bim_only)

        sky = self._sky(world_from_camera, f, cxr, cyr, Wr, Hr, lighting)
        img = np.where((depth > 0)[..., None], color.astype(np.float32), sky)
        img = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img = img * lighting.exposure + noise_rng.standard_normal(img.shape, dtype=np.float32) * 2.0
        color_out = np.clip(img + 0.5, 0, 255).astype(np.uint8)

        def near(a: NDArray) -> NDArray:
            return cv2.remap(a, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)

        seg_d = near(seg)
        bim_d = near(seg_bim)
        # Depth: inverse depth is linear in the image on planes, so interpolate it bilinearly inside surfaces and
        # fall back to the nearest sample across depth discontinuities.
        depth_near = near(depth.astype(np.float32))
        inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
        inv_lin = cv2.remap(inv, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inv_near = np.where(depth_near > 0, 1.0 / np.maximum(depth_near, 1e-6), 0.0)
        smooth = (depth_near > 0) & (np.abs(inv_lin - inv_near) <= 0.01 * inv_near)
        depth_d = np.where(smooth, 1.0 / np.maximum(inv_lin, 1e-9), depth_near).astype(np.float32)
        cat = seg_d[..., 2]
        index = seg_d[..., 0].astype(np.uint16) | (seg_d[..., 1].astype(np.uint16) << 8)
        index[cat != CAT_ELEMENT] = 0
        behind = bim_d[..., 2] == CAT_ELEMENT
        return RenderResult(color_out, index, depth_d, behind & (cat == CAT_STATIC), cat == CAT_DYNAMIC)

    def _sky(
        self, world_from_camera: F64, f: float, cx: float, cy: float, W: int, H: int, light: Lighting
    ) -> NDArray[np.float32]:
        """Sky colour per render pixel from the ray elevation and a per-day cloud layer."""
        step = 4  # evaluate on a coarse grid, upsample
        u, v = np.meshgrid(
            np.arange(0, W + step, step, dtype=np.float64), np.arange(0, H + step, step, dtype=np.float64)
        )
        rays = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1) @ world_from_camera[:3, :3].T
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        elev = np.clip(rays[..., 2], 0.0, 1.0)
        t = np.sqrt(elev)[..., None]
        zen, hor = np.array(light.sky_zenith), np.array(light.sky_horizon)
        sky = hor * (1 - t) + zen * t
        clouds = self._sky_rng_cache.get(light.cloud_seed)
        if clouds is None:
            from .textures import fractal_noise

            clouds = fractal_noise(np.random.default_rng(light.cloud_seed), 256, 512, 5, 4)
            self._sky_rng_cache = {light.cloud_seed: clouds}
        az = (np.arctan2(rays[..., 0], rays[..., 1]) / (2 * np.pi) + 0.5) * 511
        el = np.clip(elev * 2.5, 0, 1) * 255
        c = clouds[el.astype(int), az.astype(int)]
        cover = np.clip((c - (1.0 - light.cloudiness)) * 3.0, 0, 1)[..., None]
        sky = sky * (1 - cover) + np.array([235.0, 235.0, 238.0]) * (0.8 + 0.2 * c[..., None]) * cover
        big = cv2.resize(sky.astype(np.float32), (u.shape[1] * step, u.shape[0] * step), interpolation=cv2.INTER_LINEAR)
        return big[:H, :W]


def element_index_map(building: Building) -> dict[str, int]:
    """Element key -> index (1..N, building order); 0 is background."""
    return {e.key: i + 1 for i, e in enumerate(building.elements)}


def element_by_key(building: Building) -> dict[str, Element]:
    return {e.key: e for e in building.elements}
