"""User occlusion corrections: polygons (Annotation kind "occluder") that stick to a camera.

A polygon drawn on a photo of a fixed camera applies to that photo and to every frame of the same
camera captured at or after it (fixed cameras keep their pixel grid; a knocked camera needs a new
polygon). A polygon on a phone photo (no camera) applies to that photo only. Polygons are in the
pixels of the photo they were drawn on; they are rescaled when a frame has another size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class Correction:
    """One occluder polygon ((K, 2) pixels of the photo it was drawn on, whose size is ``size_px``)."""

    annotation_id: str
    photo_id: str
    camera_id: str | None
    from_time_ns: int
    polygon_px: tuple[tuple[float, float], ...]
    size_px: tuple[int, int] | None  # (width, height) of the annotated photo when known


@dataclass
class UserCorrections:
    """Store of occluder polygons and the rule deciding which frames they apply to."""

    corrections: dict[str, Correction] = field(default_factory=dict)

    def add(
        self,
        annotation_id: str,
        photo_id: str | None,
        camera_id: str | None,
        polygon_px: tuple[tuple[float, float], ...],
        photo_time_ns: int | None,
        size_px: tuple[int, int] | None,
    ) -> Correction:
        """Record a polygon (>= 3 vertices). ``photo_time_ns``: capture time of the annotated photo
        (None when unknown: then the polygon applies to all frames of the camera)."""
        if len(polygon_px) < 3:
            raise ValueError(f"occluder annotation {annotation_id}: polygon needs >= 3 vertices, got {len(polygon_px)}")
        if photo_id is None and camera_id is None:
            raise ValueError(f"occluder annotation {annotation_id}: needs a photo_id or a camera_id")
        poly = tuple((float(u), float(v)) for u, v in polygon_px)
        if not np.all(np.isfinite(np.asarray(poly))):
            raise ValueError(f"occluder annotation {annotation_id}: polygon has non-finite vertices")
        c = Correction(
            annotation_id,
            photo_id or "",
            camera_id,
            photo_time_ns if photo_time_ns is not None else -(2**62),
            poly,
            size_px,
        )
        self.corrections[annotation_id] = c
        return c

    def applies(self, c: Correction, photo_id: str, camera_id: str | None, capture_time_ns: int) -> bool:
        if c.photo_id == photo_id:
            return True
        return c.camera_id is not None and c.camera_id == camera_id and capture_time_ns >= c.from_time_ns

    def mask_for(
        self, photo_id: str, camera_id: str | None, capture_time_ns: int, width_px: int, height_px: int
    ) -> U8 | None:
        """uint8 (H, W) 0/255 union of the polygons applying to a frame, or None when none applies."""
        polys = [c for c in self.corrections.values() if self.applies(c, photo_id, camera_id, capture_time_ns)]
        if not polys:
            return None
        mask = np.zeros((height_px, width_px), np.uint8)
        for c in polys:
            pts = np.asarray(c.polygon_px, dtype=np.float64)
            if c.size_px is not None and c.size_px != (width_px, height_px):
                sx, sy = width_px / c.size_px[0], height_px / c.size_px[1]
                pts = np.stack([sx * (pts[:, 0] + 0.5) - 0.5, sy * (pts[:, 1] + 0.5) - 0.5], axis=1)
            # fillPoly with 4 fractional bits; pixel centres are integers already
            cv2.fillPoly(mask, [np.round(pts * 16).astype(np.int32)], 255, lineType=cv2.LINE_8, shift=4)
        return mask
