"""Render engine: model + schedule + photo + camera -> ``Overlay`` messages (pure core, used by node and CLI).

Holds one :class:`GLRasterizer` (EGL context, created lazily on the calling thread: always call an
engine from one thread), the current :class:`BimScene` and :class:`ScheduleView`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide.bimgeom import Mesh, glb_to_meshes
from constructaide.camera import registered_camera, scaled_intrinsics
from constructaide.imagecodec import decode_rgb, encode_png_rgb, mask_of_message
from constructaide.modelscene import BimScene, build_scene
from constructaide.modelview import GLRasterizer
from nodes.render.overlays import MODES, ScheduleView, composite, render_overlay
from nodes.render.photoreal import MaterialLibrary, PhotorealRenderer
from nodes.render.scene import filter_mask
from nodes.render.sun import sun_direction_in_site, sun_position
from schemas.messages import (
    Annotation,
    BimModel,
    BimUpdate,
    ElementFilter,
    LegendEntry,
    OcclusionMask,
    Overlay,
    Photo,
    ProgressUpdate,
    Registration,
)

ALL_MODES = (*MODES, "photoreal")


@dataclass
class RenderEngine:
    """Stateful renderer of overlays; see module docstring."""

    max_width_px: int = 1920
    presets_file: str = ""
    true_north_deg: float = 0.0
    model: BimModel | None = None
    scene: BimScene | None = None
    schedule: ScheduleView | None = None
    meshes: dict[str, Mesh] = field(default_factory=dict)
    annotations: list[Annotation] = field(default_factory=list)
    evidence: dict = field(default_factory=dict)
    _ras: GLRasterizer | None = None
    _photoreal: PhotorealRenderer | None = None

    @property
    def rasterizer(self) -> GLRasterizer:
        if self._ras is None:
            self._ras = GLRasterizer()
        return self._ras

    def set_model(self, model: BimModel) -> None:
        """Replace the model (decodes its GLB)."""
        self.meshes = glb_to_meshes(model.geometry_glb)
        self._rebuild(model)

    def apply_update(self, update: BimUpdate) -> None:
        """Apply a model diff on top of the current model (ValueError when it does not apply)."""
        if self.model is None:
            raise ValueError("BimUpdate received before any BimModel")
        if update.base_revision != self.model.revision:
            raise ValueError(f"update base {update.base_revision!r} != current revision {self.model.revision!r}")
        gone = set(update.removed) | {e.global_id for e in update.changed}
        elements = [e for e in self.model.elements if e.global_id not in gone]
        elements += list(update.changed) + list(update.added)
        self.meshes.update(glb_to_meshes(update.geometry_glb))
        model = msgspec.structs.replace(
            self.model,
            revision=update.revision,
            elements=tuple(elements),
            tasks=self.model.tasks if update.tasks is None else update.tasks,
        )
        self._rebuild(model)

    def _rebuild(self, model: BimModel) -> None:
        self.model = model
        self.scene = build_scene(model.elements, self.meshes)
        self.schedule = ScheduleView.from_model(model, self.scene)
        for ann in self.annotations:
            self.schedule.apply_annotation(ann)
        self.schedule.evidence = self.evidence

    def add_annotation(self, ann: Annotation) -> None:
        self.annotations.append(ann)
        if self.schedule is not None:
            self.schedule.apply_annotation(ann)

    def add_progress(self, update: ProgressUpdate) -> None:
        """Detected progress for the ``progress`` mode (latest estimate per element)."""
        for ep in update.elements:
            self.evidence[ep.global_id] = ep

    def render(
        self,
        photo: Photo,
        reg: Registration,
        mode: str,
        at_ns: int | None = None,
        flt: ElementFilter | None = None,
        occlusion: OcclusionMask | None = None,
        composite_photo: bool = True,
    ) -> Overlay:
        """One ``Overlay`` of ``photo`` seen by ``reg``'s camera at ``at_ns`` (default: capture time).

        ``composite_photo``: the PNG is the photo with the overlay blended in (RGB); else the RGBA
        layer alone (photoreal is always a composite).
        """
        t0 = time.perf_counter()
        if mode not in ALL_MODES:
            raise ValueError(f"unknown overlay mode {mode!r}; choose one of {', '.join(ALL_MODES)}")
        if self.scene is None or self.schedule is None or self.model is None:
            raise ValueError("no BIM model received yet")
        camera = registered_camera(reg)
        if camera is None:
            raise ValueError(f"photo {reg.photo_id} has no usable registration (status {reg.status})")
        if reg.photo_id != photo.photo_id:
            raise ValueError(f"registration is for {reg.photo_id}, photo is {photo.photo_id}")
        # The pixels are needed only to composite (an RGBA layer needs the size alone, which the message carries).
        img: NDArray[np.uint8] | None = None
        if composite_photo or mode == "photoreal" or photo.width_px <= 0 or photo.height_px <= 0:
            img = decode_rgb(photo.data, f"photo {photo.photo_id}")
            h, w = img.shape[:2]
        else:
            h, w = photo.height_px, photo.width_px
        intr = camera.intrinsics
        if (intr.width_px, intr.height_px) != (w, h):
            intr = scaled_intrinsics(intr, w, h)
        if w > self.max_width_px:
            w, h = self.max_width_px, round(h * self.max_width_px / w)
            img = None if img is None else np.asarray(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), np.uint8)
            intr = scaled_intrinsics(intr, w, h)
        wfc = camera.world_from_camera
        at = photo.capture_time_ns if at_ns is None else at_ns
        occ = mask_of_message(occlusion, (h, w))
        ground_z = self.model.terrain_height_m if self.model.terrain_height_m is not None else 0.0
        legend: tuple[LegendEntry, ...]
        if mode == "photoreal":
            if self._photoreal is None:
                lib = MaterialLibrary.from_toml(self.presets_file) if self.presets_file else MaterialLibrary()
                self._photoreal = PhotorealRenderer(self.rasterizer, lib)
            gps = self.model.gps or photo.gps
            if gps is not None:
                sun = sun_position(gps.lat_deg, gps.lon_deg, at)
                sun_dir = sun_direction_in_site(sun, self.true_north_deg)
                label = f"sun az {sun.azimuth_deg:.1f} deg, el {sun.elevation_deg:.1f} deg"
            else:
                sun_dir = np.array([0.3, -0.5, 0.8])
                label = "sun: default direction (model has no GPS position)"
            visible = self.schedule.built(at, basis="planned")
            if flt is not None:
                visible &= filter_mask(self.scene, flt, self.schedule.task_elements)
            assert img is not None
            out = self._photoreal.render(
                self.scene, visible, intr, wfc, img, sun_dir, occlusion=occ, ground_z_m=ground_z
            )
            legend = (LegendEntry(label=label, rgba=(255, 220, 120, 255)),)
        else:
            res = render_overlay(self.rasterizer, self.scene, self.schedule, intr, wfc, mode, at, flt, occ, ground_z)
            out = composite(img, res.layer_rgba) if img is not None and composite_photo else res.layer_rgba
            legend = res.legend
        return Overlay(
            site=photo.site,
            photo_id=photo.photo_id,
            mode=mode,  # type: ignore[arg-type]
            at_ns=at,
            image_png=encode_png_rgb(out),
            legend=legend,
            filter=flt or ElementFilter(),
            camera_id=photo.camera_id,
            processing_ms=(time.perf_counter() - t0) * 1000.0,
        )

    def close(self) -> None:
        if self._ras is not None:
            self._ras.close()
            self._ras = None
            self._photoreal = None


def presets_path_ok(path: str) -> str:
    """``path`` if it names a readable file (or is empty), else ValueError."""
    if path and not Path(path).is_file():
        raise ValueError(f"presets file {path!r} does not exist")
    return path
