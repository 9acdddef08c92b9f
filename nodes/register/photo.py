"""A photo handed to registration: lazily decoded pixels and its metadata."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from constructaide.imagecodec import decode_bgr, decode_gray
from schemas.messages import GeoPoint


class FrameImage:
    """A photo's pixels, decoded lazily: a reduced grey decode for tracking, a full decode only when needed."""

    def __init__(self, data: bytes | None = None, image: np.ndarray | None = None) -> None:
        if data is None and image is None:
            raise ValueError("FrameImage needs encoded bytes or a decoded image")
        self._data = data
        self._bgr: np.ndarray | None = None
        self._gray: np.ndarray | None = None
        self._small: dict[float, np.ndarray] = {}
        if image is not None:
            img = np.asarray(image)
            if img.dtype != np.uint8 or img.ndim not in (2, 3):
                raise ValueError(f"expected a uint8 grey or BGR image, got {img.dtype} {img.shape}")
            self._bgr = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)

    def _encoded(self) -> bytes:
        assert self._data is not None
        return self._data

    def bgr(self) -> np.ndarray:
        """Full-resolution BGR uint8 (H, W, 3)."""
        if self._bgr is None:
            self._bgr = decode_bgr(self._encoded(), "photo")
        return self._bgr

    def gray(self) -> np.ndarray:
        """Full-resolution grey uint8 (H, W)."""
        if self._gray is None:
            self._gray = cv2.cvtColor(self.bgr(), cv2.COLOR_BGR2GRAY)
        return self._gray

    def gray_small(self, scale: float) -> np.ndarray:
        """Grey image at ``scale`` of full resolution; 0.5 decodes JPEG directly at half size (fast)."""
        if scale not in self._small:
            if scale == 0.5 and self._data is not None and self._bgr is None:
                self._small[scale] = decode_gray(self._encoded(), "photo", reduced=2)
            elif scale == 1.0:
                self._small[scale] = self.gray()
            else:
                g = self.gray()
                size = (round(g.shape[1] * scale), round(g.shape[0] * scale))
                self._small[scale] = cv2.resize(g, size, interpolation=cv2.INTER_AREA)
        return self._small[scale]


@dataclass
class PhotoInput:
    """One photo handed to the registrar. ``focal_px`` is an EXIF prior (full-resolution pixels) or None; ``gps``
    its EXIF position or None."""

    photo_id: str
    image: FrameImage
    camera_id: str | None = None
    capture_time_ns: int = 0
    focal_px: float | None = None
    width_px: int = 0
    height_px: int = 0
    gps: GeoPoint | None = None
