"""Photoreal composite (paper Sec. 4.2): PBR materials, sun + sky light, shadows, differential rendering.

Materials: BIM material names map to a preset library of metallic-roughness materials by keyword
(``concrete``, ``brick``, ``glass``, ...); unknown names fall back by IFC class, then to
``concrete``. Presets are swappable from a TOML file::

    [presets.brick]              # overrides / adds a preset
    base_rgb = [0.55, 0.25, 0.18]
    metallic = 0.0
    roughness = 0.9
    alpha = 1.0
    keywords = ["brick", "masonry"]
    [lighting]
    sun_intensity = 4.0
    sky_rgb = [0.33, 0.36, 0.42]

Lighting: a directional sun (direction from :mod:`sun`) with pyrender's shadow mapping, and the
sky as a uniform ambient term. Compositing follows Karsch et al. 2011: the BIM is rendered over a
local ground proxy (a plane at the terrain height) with and without the BIM; outside the
rendered object the photo receives ``photo + (with - without)``, where the proxy's albedo is taken
from the photo itself (so the difference is ``photo * (with / without - 1)``: shadows darken the
real ground by the rendered factor); inside the object the rendered object replaces the photo.
Pixels marked occluded keep the photo.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.camera import focal_xy
from constructaide.modelscene import BimScene
from constructaide.modelview import GLRasterizer, render_geometry
from schemas.messages import BimElement, Intrinsics

# pyrender 0.1.45 computes scene bounds (needed for shadow maps) with ``np.infty``, removed in NumPy 2.
if "infty" not in np.__dict__:
    setattr(np, "infty", np.inf)  # noqa: B010

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class MaterialPreset:
    """Metallic-roughness material; ``base_rgb`` linear in [0, 1]."""

    name: str
    base_rgb: tuple[float, float, float]
    metallic: float = 0.0
    roughness: float = 0.8
    alpha: float = 1.0
    keywords: tuple[str, ...] = ()


@dataclass(frozen=True)
class Lighting:
    sun_intensity: float = 4.0
    sky_rgb: tuple[float, float, float] = (0.33, 0.36, 0.42)
    shadows: bool = True


DEFAULT_PRESETS: dict[str, MaterialPreset] = {
    p.name: p
    for p in (
        MaterialPreset("concrete", (0.52, 0.51, 0.48), 0.0, 0.9, 1.0, ("concrete", "beton", "cement", "c30", "c25")),
        MaterialPreset("brick", (0.50, 0.22, 0.15), 0.0, 0.9, 1.0, ("brick", "masonry", "ziegel", "baksteen", "clay")),
        MaterialPreset("glass", (0.10, 0.16, 0.20), 0.0, 0.05, 0.55, ("glass", "glazing", "glas", "pane")),
        MaterialPreset("steel", (0.45, 0.46, 0.48), 1.0, 0.4, 1.0, ("steel", "metal", "alu", "stahl", "iron", "s235")),
        MaterialPreset("timber", (0.45, 0.30, 0.17), 0.0, 0.7, 1.0, ("timber", "wood", "holz", "hout", "oak", "pine")),
        MaterialPreset("render", (0.80, 0.78, 0.72), 0.0, 0.95, 1.0, ("render", "plaster", "putz", "stucco", "paint")),
        MaterialPreset("tile", (0.42, 0.16, 0.10), 0.0, 0.6, 1.0, ("tile", "roof", "dachziegel", "pan")),
        MaterialPreset("insulation", (0.85, 0.80, 0.35), 0.0, 1.0, 1.0, ("insulation", "eps", "mineral wool")),
        MaterialPreset("stone", (0.60, 0.58, 0.55), 0.0, 0.8, 1.0, ("stone", "granite", "limestone", "sand-lime")),
    )
}

CLASS_FALLBACK: dict[str, str] = {
    "IfcWindow": "glass",
    "IfcCurtainWall": "glass",
    "IfcPlate": "glass",
    "IfcBeam": "steel",
    "IfcMember": "steel",
    "IfcRailing": "steel",
    "IfcDoor": "timber",
    "IfcRoof": "tile",
    "IfcCovering": "render",
    "IfcWall": "brick",
    "IfcWallStandardCase": "brick",
}


@dataclass
class MaterialLibrary:
    presets: dict[str, MaterialPreset] = field(default_factory=lambda: dict(DEFAULT_PRESETS))
    lighting: Lighting = field(default_factory=Lighting)

    @classmethod
    def from_toml(cls, path: str | Path) -> MaterialLibrary:
        """Defaults overridden by a TOML file (see module docstring). Raises ValueError on bad content."""
        try:
            data = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"cannot read material presets {path}: {exc}") from exc
        lib = cls()
        for name, spec in data.get("presets", {}).items():
            base = lib.presets.get(name, MaterialPreset(name, (0.6, 0.6, 0.6)))
            try:
                lib.presets[name] = replace(
                    base,
                    base_rgb=tuple(float(v) for v in spec.get("base_rgb", base.base_rgb)),  # type: ignore[arg-type]
                    metallic=float(spec.get("metallic", base.metallic)),
                    roughness=float(spec.get("roughness", base.roughness)),
                    alpha=float(spec.get("alpha", base.alpha)),
                    keywords=tuple(str(k).lower() for k in spec.get("keywords", base.keywords)),
                )
            except (TypeError, ValueError) as exc:
                raise ValueError(f"bad preset {name!r} in {path}: {exc}") from exc
            if len(lib.presets[name].base_rgb) != 3:
                raise ValueError(f"preset {name!r} in {path}: base_rgb needs 3 values")
        light = data.get("lighting", {})
        lib.lighting = Lighting(
            sun_intensity=float(light.get("sun_intensity", lib.lighting.sun_intensity)),
            sky_rgb=tuple(float(v) for v in light.get("sky_rgb", lib.lighting.sky_rgb)),  # type: ignore[arg-type]
            shadows=bool(light.get("shadows", lib.lighting.shadows)),
        )
        return lib

    def preset_for(self, element: BimElement) -> MaterialPreset:
        """Preset by keyword in the material name, else by IFC class, else ``concrete``."""
        name = element.material.lower()
        if name:
            for p in self.presets.values():
                if any(k in name for k in p.keywords):
                    return p
        fallback = CLASS_FALLBACK.get(element.ifc_class)
        if fallback and fallback in self.presets:
            return self.presets[fallback]
        return self.presets.get("concrete", next(iter(self.presets.values())))


def _srgb_to_linear(x: NDArray[np.float32]) -> NDArray[np.float32]:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _linear_to_srgb(x: NDArray[np.float32]) -> NDArray[np.float32]:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


class PhotorealRenderer:
    """Builds pyrender scenes from a :class:`BimScene` and composites renders into photos.

    Uses the rasterizer's EGL context (same thread). Scenes are cached per visible set.
    """

    def __init__(self, rasterizer: GLRasterizer, library: MaterialLibrary | None = None) -> None:
        self.rasterizer = rasterizer
        self.library = library or MaterialLibrary()
        self._cache_key: tuple | None = None
        self._scenes: tuple[Any, Any] | None = None

    def _build(self, scene: BimScene, visible: NDArray[np.bool_], ground_z_m: float):
        import pyrender
        import trimesh

        key = (id(scene), visible.tobytes(), ground_z_m, id(self.library))
        if self._cache_key == key and self._scenes is not None:
            return self._scenes
        groups: dict[str, list[int]] = {}
        for i in np.nonzero(visible[1:])[0] + 1:
            groups.setdefault(self.library.preset_for(scene.elements[i - 1]).name, []).append(int(i))
        with_bim = pyrender.Scene(bg_color=(0, 0, 0, 0), ambient_light=self.library.lighting.sky_rgb)
        without = pyrender.Scene(bg_color=(0, 0, 0, 0), ambient_light=self.library.lighting.sky_rgb)
        for name, idx in groups.items():
            pos = np.vstack([scene.element_vertices(i) for i in idx]).astype(np.float64)
            if not len(pos):
                continue
            faces = np.arange(len(pos)).reshape(-1, 3)
            mesh_t = trimesh.Trimesh(vertices=pos, faces=faces, process=False)
            p = self.library.presets[name]
            mat = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*p.base_rgb, p.alpha),
                metallicFactor=p.metallic,
                roughnessFactor=p.roughness,
                alphaMode="BLEND" if p.alpha < 1.0 else "OPAQUE",
                doubleSided=True,
            )
            with_bim.add(pyrender.Mesh.from_trimesh(mesh_t, material=mat, smooth=False))
        # Local ground proxy: a square around the building (kept modest so the shadow map stays sharp).
        c = 0.5 * (scene.bbox_min_m + scene.bbox_max_m)
        half = 1.5 * float(np.max(scene.bbox_max_m[:2] - scene.bbox_min_m[:2])) + 10.0
        quad = np.array(
            [
                [c[0] - half, c[1] - half, ground_z_m],
                [c[0] + half, c[1] - half, ground_z_m],
                [c[0] + half, c[1] + half, ground_z_m],
                [c[0] - half, c[1] + half, ground_z_m],
            ]
        )
        ground = trimesh.Trimesh(vertices=quad, faces=[[0, 1, 2], [0, 2, 3]], process=False)
        gmat = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=(0.5, 0.5, 0.5, 1.0), metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True
        )
        for s in (with_bim, without):
            s.add(pyrender.Mesh.from_trimesh(ground, material=gmat, smooth=False))
        self._scenes = (with_bim, without)
        self._cache_key = key
        return self._scenes

    def render(
        self,
        scene: BimScene,
        visible: NDArray[np.bool_],
        intr: Intrinsics,
        world_from_camera: NDArray[np.float64],
        photo_rgb: NDArray[np.uint8],
        sun_dir_world: NDArray[np.float64],
        occlusion: NDArray[np.bool_] | None = None,
        ground_z_m: float = 0.0,
    ) -> NDArray[np.uint8]:
        """Composite (H, W, 3) uint8 of the visible elements rendered into ``photo_rgb``.

        ``sun_dir_world``: unit vector towards the sun (site frame, z up); a sun below the horizon
        leaves only sky light.
        """
        import pyrender

        h, w = intr.height_px, intr.width_px
        if photo_rgb.shape[:2] != (h, w):
            raise ValueError(f"photo {photo_rgb.shape[:2]} does not match intrinsics ({h}, {w})")
        with_bim, without = self._build(scene, visible, ground_z_m)
        geo = render_geometry(intr)
        ri = geo.render_intrinsics
        fx, fy = focal_xy(ri)
        cam = pyrender.IntrinsicsCamera(
            fx,
            fy,
            ri.cx_px + 0.5,
            ri.cy_px + 0.5,
            znear=0.05,
            zfar=float(np.linalg.norm(scene.bbox_max_m - scene.bbox_min_m)) * 10 + 500,
        )
        pose = np.asarray(world_from_camera, np.float64) @ _GL_FROM_CV
        s = np.asarray(sun_dir_world, np.float64)
        s = s / np.linalg.norm(s)
        z = s
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
        sun_pose = np.eye(4)
        sun_pose[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        intensity = self.library.lighting.sun_intensity * float(np.clip(s[2] * 4.0, 0.0, 1.0))
        off = self.rasterizer.offscreen
        flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL if self.library.lighting.shadows else pyrender.RenderFlags.NONE
        # The background-only render (ground proxy + its own shadows: smooth) is made at half resolution.
        half = pyrender.IntrinsicsCamera(
            fx / 2, fy / 2, (ri.cx_px + 0.5) / 2, (ri.cy_px + 0.5) / 2, znear=cam.znear, zfar=cam.zfar
        )
        full_size = (ri.width_px, ri.height_px)
        half_size = ((ri.width_px + 1) // 2, (ri.height_px + 1) // 2)
        outs = []
        for sc, cm, size in ((with_bim, cam, full_size), (without, half, half_size)):
            off.viewport_width, off.viewport_height = size
            cn = sc.add(cm, pose=pose)
            ln = sc.add(pyrender.DirectionalLight(color=np.ones(3), intensity=intensity), pose=sun_pose)
            try:
                color, depth = off.render(sc, flags=flags)
            finally:
                sc.remove_node(cn)
                sc.remove_node(ln)
            if size != full_size:
                color = cv2.resize(color, full_size, interpolation=cv2.INTER_LINEAR)
                depth = cv2.resize(depth, full_size, interpolation=cv2.INTER_NEAREST)
            outs.append((color, depth))
        (c_with, _), (c_without, d_without) = outs

        def warp(img: NDArray, interp: int) -> NDArray:
            if geo.map_x is None:
                return img
            return cv2.remap(img, geo.map_x, geo.map_y, interp, borderMode=cv2.BORDER_REPLICATE)

        lin_with = _srgb_to_linear(warp(c_with, cv2.INTER_LINEAR).astype(np.float32) / 255.0)
        lin_without = _srgb_to_linear(warp(c_without, cv2.INTER_LINEAR).astype(np.float32) / 255.0)
        ground = warp((d_without > 0).astype(np.uint8), cv2.INTER_NEAREST) > 0
        if geo.outside is not None:
            ground &= ~geo.outside  # rays the render does not cover show the photo alone
        ids = self.rasterizer.render(scene, intr, world_from_camera, visible).ids
        obj = ids > 0
        free = np.ones((h, w), bool) if occlusion is None else ~occlusion
        photo_lin = _srgb_to_linear(photo_rgb.astype(np.float32) / 255.0)
        # Differential rendering with the proxy's albedo taken from the photo: photo * with / without.
        ratio = np.ones_like(photo_lin)
        np.divide(lin_with, np.maximum(lin_without, 1e-4), out=ratio, where=ground[..., None])
        ratio = np.clip(ratio, 0.0, 1.5)
        out = photo_lin * np.where((ground & ~obj & free)[..., None], ratio, 1.0)
        inside = (obj & free)[..., None]
        out = np.where(inside, lin_with, out)
        return np.clip(_linear_to_srgb(out) * 255.0 + 0.5, 0, 255).astype(np.uint8)
