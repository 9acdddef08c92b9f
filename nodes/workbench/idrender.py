"""Element-index and depth images of the model seen by a photo's camera, for the workbench (selection by region,
annotation transfer, peeks): the shared :class:`constructaide.modelview.GLRasterizer` at the photo's size scaled to
at most ``max_width_px``, lens distortion included.

Outputs at the scaled photo size: ``ids`` int32 (h, w), element index + 1 (0 = nothing); ``depth_m`` float32
(h, w), camera z in metres (0 = nothing). The EGL context is thread-bound: create and use an :class:`IdRenderer`
on one thread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.modelview import GLRasterizer
from nodes.workbench.geometry import ModelGeometry
from schemas.messages import Intrinsics


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


def intrinsics_scaled_by(intr: Intrinsics, scale: float) -> Intrinsics:
    """The same camera for its image resized by ``scale`` (sizes rounded)."""
    return cam.scaled_intrinsics(intr, max(1, round(intr.width_px * scale)), max(1, round(intr.height_px * scale)))


class IdRenderer:
    """ID / depth renders of one :class:`ModelGeometry` (see module docstring); owns one EGL context."""

    def __init__(self, geometry: ModelGeometry) -> None:
        self.geometry = geometry
        self._raster = GLRasterizer()

    def render(self, camera: cam.PinholeCamera, visible: NDArray[np.bool_], max_width_px: int = 960) -> IdImage:
        """IDs and depth of the ``visible`` (E,) elements seen by ``camera``, at most ``max_width_px`` wide."""
        intr = camera.intrinsics
        scale = min(1.0, max_width_px / intr.width_px)
        intr_s = intrinsics_scaled_by(intr, scale) if scale < 1.0 else intr
        drawn = np.concatenate([[False], np.asarray(visible, bool)])
        res = self._raster.render(self.geometry.scene, intr_s, camera.world_from_camera, drawn)
        return IdImage(ids=res.ids.astype(np.int32), depth_m=np.asarray(res.depth_m, np.float32), scale=scale)

    def close(self) -> None:
        self._raster.close()
